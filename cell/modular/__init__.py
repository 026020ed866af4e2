"""The modular robot of seed 002: six joint modules moved by Virtual Decomposition Control."""
