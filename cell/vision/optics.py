"""Close-range optics: a thin lens turns distance from the focus plane into blur, and a sensor adds noise.

For a lens of focal length f at f-number N focused at distance s, a point
at distance d is imaged as a disc (the circle of confusion) of diameter

    c = (f / N) * |d - s| / d * f / (s - f)

on the sensor; divided by the pixel pitch it is the blur in pixels.  The
rendered image is sharp everywhere, so the blur of the object of interest
(the calibration card, planar and facing the camera) is applied to the whole
frame.  The point spread function is the Gaussian with the disc's second
moment (sigma = c / (2 sqrt 2)), as in depth-from-defocus work since
Pentland (1987): a disc sampled on whole pixels is no blur at all below a
pixel, and the sharpness near focus would go flat.  Then Gaussian read noise
and 8-bit quantisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class ThinLens:
    focal_mm: float = 35.0
    f_number: float = 2.0
    focus_mm: float = 350.0  # where the lens is focused, from the lens
    pixel_um: float = 11.25  # the sensor's pixel pitch at the rendered resolution

    def coc_px(self, distance_mm: float) -> float:
        """The blur disc's diameter in pixels for a point `distance_mm` from the lens."""
        f, s, d = self.focal_mm, self.focus_mm, distance_mm
        if d <= f or s <= f:
            return math.inf
        c_mm = (f / self.f_number) * abs(d - s) / d * f / (s - f)
        return c_mm * 1000.0 / self.pixel_um

    def sensor_mm(self, pixels: int) -> float:
        return pixels * self.pixel_um / 1000.0

    def fovy_deg(self, height_px: int) -> float:
        """The vertical field of view at the focus distance (the image distance is f s / (s - f))."""
        image_mm = self.focal_mm * self.focus_mm / (self.focus_mm - self.focal_mm)
        return math.degrees(2 * math.atan(self.sensor_mm(height_px) / 2 / image_mm))


def psf_sigma(diameter_px: float) -> float:
    """The Gaussian PSF's sigma for a blur disc of that diameter (the same second moment)."""
    return diameter_px / (2.0 * math.sqrt(2.0))


def defocus(sharp: np.ndarray, blur_px: float) -> np.ndarray:
    """The sharp render blurred by the lens (float32 grey levels), before the sensor's noise."""
    img: np.ndarray = sharp.astype(np.float32)
    sigma = psf_sigma(blur_px)
    if sigma > 0.05:
        k = max(3, 2 * math.ceil(3 * sigma) + 1)  # (OpenCV's own size would be 1 below sigma 0.3)
        img = cv2.GaussianBlur(img, (k, k), sigma, borderType=cv2.BORDER_REPLICATE)
    return img


def quantise(img: np.ndarray) -> np.ndarray:
    """Grey levels to the sensor's 8 bits, rounded."""
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def expose(sharp: np.ndarray, blur_px: float, noise_dn: float, rng: np.random.Generator) -> np.ndarray:
    """The frame the sensor gives: the sharp render blurred by the lens, with read noise, in 8 bits."""
    img = defocus(sharp, blur_px)
    if noise_dn > 0:
        img += rng.normal(0.0, noise_dn, img.shape).astype(np.float32)
    return quantise(img)


class ReadNoise:
    """A sensor's read noise for a stream of frames: each frame's is a window at a random offset into
    one field of Gaussian noise twice the frame's size, drawn once.

    Drawing a 640x480 frame's noise afresh took 10 ms, a sixth of a frame's whole cost; a window is
    a view (nothing drawn), and of the field's (h+1)(w+1) windows two frames share one rarely, and
    never in a way a sharpness measure or an average of frames could see."""

    def __init__(self, shape: tuple[int, int], noise_dn: float, rng: np.random.Generator) -> None:
        h, w = shape
        self.shape, self.rng = shape, rng
        self.field = rng.standard_normal((2 * h, 2 * w), dtype=np.float32) * np.float32(noise_dn)

    def add_to(self, img: np.ndarray) -> np.ndarray:
        """img (float32, the frame's shape) with a fresh window of noise added: a new array."""
        h, w = self.shape
        i, j = int(self.rng.integers(0, h + 1)), int(self.rng.integers(0, w + 1))
        out: np.ndarray = img + self.field[i : i + h, j : j + w]
        return out
