"""Vision in the cell: a simulated close-range camera, its frame buffer, and the sharpness pipeline."""
