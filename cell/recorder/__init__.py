"""Drawing the cell in Rerun."""
