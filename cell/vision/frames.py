"""The image acquisition service's circular buffer: recent frames, and the one closest to an instant.

As in the paper's FxIS-based ImAcqService, acquisition runs continuously
(here in a thread of its own) and a vision request is answered from the
buffer with the frame taken closest in time to the request, so a request
never waits for an exposure it could have had already, and a frame that
shows the robot before it stopped is never taken for one after.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Frame:
    t_ns: int  # the instant it shows (CLOCK_MONOTONIC)
    image: np.ndarray  # 8-bit grayscale
    truth_distance_mm: float  # the simulator's truth, for evaluation
    blur_px: float
    render_ns: int


class FrameBuffer:
    """Thread-safe: the camera thread adds, the event loop looks up."""

    def __init__(self, size: int) -> None:
        self._frames: deque[Frame] = deque(maxlen=size)
        self._lock = threading.Lock()
        self.added = 0

    def add(self, frame: Frame) -> None:
        with self._lock:
            self._frames.append(frame)
            self.added += 1

    def newest(self) -> Frame | None:
        with self._lock:
            return self._frames[-1] if self._frames else None

    def closest(self, t_ns: int) -> Frame | None:
        """The frame whose instant is nearest `t_ns` (the later one on a tie); None if empty."""
        with self._lock:
            frames = list(self._frames)
        if not frames:
            return None
        return min(reversed(frames), key=lambda f: abs(f.t_ns - t_ns))
