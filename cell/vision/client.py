"""Vision requests from task scripts: `await cell.vision.request()` (the paper's ProtobufCommunicator).

Each request goes to the `vision` service over the bus, matched by id, and
its life (sent, answered) is published on `run/vision/request` like a robot
request's, so that vision (orange) and robot (blue) requests share one Gantt
chart (Fig. 10).  A frame with no calibration object in it is an answer
(`found` False, with the reason), not an exception.
"""

from __future__ import annotations

import itertools
import os
import time
from dataclasses import dataclass

from cell.bus import Bus
from cell.v1 import skills_pb2, vision_pb2


@dataclass(frozen=True)
class Measurement:
    id: str
    found: bool
    sharpness: float
    reason: str
    frame_t_ns: int  # the instant the frame shows (CLOCK_MONOTONIC)
    sent_ns: int
    received_ns: int
    truth_distance_mm: float  # the simulator's truth: for evaluating a calibration, not for using it


class VisionClient:
    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self._ids = itertools.count(int.from_bytes(os.urandom(3), "big") << 8)

    async def request(self, t_ns: int | None = None, timeout: float = 5.0) -> Measurement:
        """The sharpness of the frame closest to `t_ns` (default: now, the request's own instant)."""
        rid = f"{next(self._ids) & 0xFFFFFFFF:08x}"
        sent = time.monotonic_ns()
        req = vision_pb2.VisionRequest(id=rid, t_ns=t_ns or sent)
        try:
            r = await self.bus.request("vision", "measure", req, vision_pb2.VisionReply, timeout)
        except Exception as exc:
            self._trace(rid, sent, time.monotonic_ns(), "error", type(exc).__name__)
            raise
        got = time.monotonic_ns()
        self._trace(rid, sent, got, "done" if r.found else "error", "" if r.found else "no_object")
        return Measurement(rid, r.found, r.sharpness, r.reason, r.frame_t_ns, sent, got, r.truth_distance_mm)

    async def info(self, timeout: float = 5.0) -> vision_pb2.CameraInfo:
        return await self.bus.request(
            "vision", "info", vision_pb2.VisionInfoRequest(), vision_pb2.CameraInfo, timeout
        )

    def _trace(self, rid: str, sent: int, got: int, status: str, code: str) -> None:
        trace = skills_pb2.RequestTrace(
            robot="vision", id=rid, skill="measure", sent_ns=sent, received_ns=got, status=status, code=code
        )
        self.bus.publish("run/vision/request", trace)
