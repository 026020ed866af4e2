"""SnP (SpW-SnP-MR): time-bounded queries (SnP-MrT), time sync (SnP-TSP), PID management."""
