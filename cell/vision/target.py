"""The Adept paper's planar calibration object (Fig. 6): nested rectangles, thin black borders on white."""

from __future__ import annotations

import numpy as np

WIDTH_MM, HEIGHT_MM = 40.0, 30.0  # the card
LINE_MM = 0.3  # the borders' width
RINGS = 5  # rectangles, one inside the other


def target_image(
    px_per_mm: float = 20.0, width_mm: float = WIDTH_MM, height_mm: float = HEIGHT_MM
) -> np.ndarray:
    """The card as an 8-bit grayscale image (white 255, lines 0), `px_per_mm` pixels per mm."""
    w, h = round(width_mm * px_per_mm), round(height_mm * px_per_mm)
    img = np.full((h, w), 255, np.uint8)
    line = max(1, round(LINE_MM * px_per_mm))
    margin_x, margin_y = w / (2 * RINGS + 2), h / (2 * RINGS + 2)
    for k in range(1, RINGS + 1):
        x0, y0 = round(k * margin_x), round(k * margin_y)
        x1, y1 = w - x0, h - y0
        img[y0 : y0 + line, x0:x1] = 0
        img[y1 - line : y1, x0:x1] = 0
        img[y0:y1, x0 : x0 + line] = 0
        img[y0:y1, x1 - line : x1] = 0
    return img
