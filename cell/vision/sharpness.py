"""The Adept paper's sharpness measurement (Fig. 7), step by step with OpenCV: the ImProcNode.

Each step is a function named after the paper's token it produces, so that
each can be tested on images the tests make:

    image -> highlight_light -> erosion -> find_ccomp -> identify_object_region
          -> crop_roi -> sobel_x -> h_profile_sobelx -> measure_sharpness

The erosion step removes the calibration card's thin black lines from the
light mask (it erodes the dark: a closing of the light regions), so that the
whole card is one connected component; the card is then the component whose
width-to-height ratio lies in a range, whose area is large enough and which
lies whole inside the frame.  When
no component qualifies the answer is `found=False` with the reason, never an
exception.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class Params:
    """The pre-defined configuration tokens of Fig. 7."""

    light_threshold: int = 190  # gray level above which a pixel is light (the card ~250, the flange ~135)
    erosion_px: int = 9  # kernel removing dark lines this thin or thinner
    ratio_range: tuple[float, float] = (1.1, 1.6)  # the card's width / height (40 x 30 mm: 1.33)
    min_area_px: int = 4000


@dataclass
class Result:
    found: bool
    sharpness: float = 0.0
    reason: str = ""
    roi: tuple[int, int, int, int] = (0, 0, 0, 0)  # x, y, w, h of the card in the image
    profile: np.ndarray = field(default_factory=lambda: np.zeros(0))  # profile_sx


def highlight_light(image: np.ndarray, p: Params) -> np.ndarray:
    _, mask = cv2.threshold(image, p.light_threshold, 255, cv2.THRESH_BINARY)
    return mask


def erosion(thresholded_light: np.ndarray, p: Params) -> np.ndarray:
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (p.erosion_px, p.erosion_px))
    return cv2.morphologyEx(thresholded_light, cv2.MORPH_CLOSE, k)


def find_ccomp(eroded: np.ndarray) -> np.ndarray:
    """Connected components' stats: one row per component (background first) of x, y, w, h, area."""
    _n, _labels, stats, _centroids = cv2.connectedComponentsWithStats(eroded, connectivity=8)
    return stats


def identify_object_region(
    ccomp: np.ndarray, p: Params, shape: tuple[int, ...]
) -> tuple[int, int, int, int] | None:
    """The largest component with the card's aspect ratio and at least the minimal area, whole in the
    frame (one cut by the frame's edge may be anything light, and is no card to measure)."""
    best = None
    lo, hi = p.ratio_range
    rows, cols = shape[:2]
    for x, y, w, h, area in ccomp[1:]:
        if h == 0 or area < p.min_area_px or not lo <= w / h <= hi:
            continue
        if x == 0 or y == 0 or x + w >= cols or y + h >= rows:
            continue
        if best is None or area > best[4]:
            best = (int(x), int(y), int(w), int(h), int(area))
    return None if best is None else best[:4]


def crop_roi(image: np.ndarray, roi: tuple[int, int, int, int]) -> np.ndarray:
    x, y, w, h = roi
    return image[y : y + h, x : x + w]


def sobel_x(roi_image: np.ndarray) -> np.ndarray:
    return cv2.Sobel(roi_image, cv2.CV_32F, 1, 0, ksize=3)


def h_profile_sobelx(sobelx_im: np.ndarray) -> np.ndarray:
    return sobelx_im[sobelx_im.shape[0] // 2]


def measure_sharpness(profile_sx: np.ndarray) -> float:
    return float(np.std(profile_sx))


def sharpness(image: np.ndarray, p: Params | None = None) -> Result:
    """The whole graph on an 8-bit grayscale (or BGR) image."""
    p = p or Params()
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8 or image.size == 0:
        return Result(False, reason="the image is not an 8-bit picture")
    region = identify_object_region(find_ccomp(erosion(highlight_light(image, p), p)), p, image.shape)
    if region is None:
        return Result(False, reason="no calibration object in view")
    profile = h_profile_sobelx(sobel_x(crop_roi(image, region)))
    return Result(True, measure_sharpness(profile), roi=region, profile=profile)
