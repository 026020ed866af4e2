"""The UR controller's own interfaces on the cell's arms (RTDE, the dashboard server): docs/ur.md."""
