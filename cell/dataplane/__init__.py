"""The in-network velocity controller: a software data plane doing what the P4 switch does (NSDI'22)."""
