"""The industrial controller: plans motions and loads them into the data plane as TPs."""
