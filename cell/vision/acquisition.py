"""The Adept paper's ImAcqService and ImProcNode on one simulated camera.

A thread of its own (Acquisition) renders the camera's view of the watched
robot at its latest joint positions at [vision] fps, into a circular buffer of
recent frames stamped with the instant of the robot state they show.  Vision
answers the requests: the sharpness (Fig. 7) of the frame closest in time to
a request's instant, waiting for the next frame (at most WAIT_PERIODS) when the
newest is older than that instant, so a request made after a motion never
gets a picture from before it; and the camera's geometry and frame rate.
services/vision.py serves it on the bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cell.bus import FaultCode, RpcFault
from cell.config import RobotConfig, VisionConfig
from cell.counters import Counters
from cell.v1 import vision_pb2
from cell.vision import sharpness
from cell.vision.camera import Camera, CameraSpec
from cell.vision.frames import Frame, FrameBuffer
from cell.vision.optics import ThinLens

WAIT_PERIODS = 2  # a request for an instant newer than every frame waits at most this many frames


def camera_spec(v: VisionConfig) -> CameraSpec:
    """The camera and its lens as [vision] describes them."""
    lens = ThinLens(v.focal_mm, v.f_number, v.focus_mm, v.pixel_um)
    (x, y, z), (ax, ay, az) = v.position_m, v.axis  # (3-vectors: the config checks them)
    return CameraSpec((x, y, z), (ax, ay, az), v.width_px, v.height_px, lens, v.noise_dn)


class Acquisition:
    """The camera thread: renders at the frame rate, on absolute deadlines, into the buffer."""

    def __init__(
        self, spec: CameraSpec, q0: np.ndarray, fps: float, buffer: FrameBuffer, model: str = "ur5e"
    ) -> None:
        self.spec, self.fps, self.buffer, self.model = spec, fps, buffer, model
        # the joint positions to render and their instant (0: none heard yet, q0), swapped as one
        self.state: tuple[np.ndarray, int] = (np.array(q0, float), 0)
        self.error: BaseException | None = None
        self.frames_per_s = 0.0
        self.late = 0
        self.renders = 0  # frames rendered anew; the others showed a still scene (Camera.capture)
        self._stop = threading.Event()
        self._ready = threading.Event()
        self.on_frame = lambda _f: None
        self.thread = threading.Thread(target=self._run, name="camera", daemon=True)

    def start(self, timeout: float = 60.0) -> None:
        self.thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError("the camera did not come up")
        if self.error is not None:
            raise RuntimeError(f"the camera failed: {self.error}") from self.error

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5)

    def _run(self) -> None:
        try:
            cam = Camera(self.spec, self.model)
        except BaseException as exc:  # no GL here, a bad model: said once, by start()
            self.error = exc
            self._ready.set()
            return
        self._ready.set()
        period = 1e9 / self.fps
        t0 = time.monotonic_ns()
        n, window = 0, []
        try:
            while not self._stop.is_set():
                t_render = time.monotonic_ns()
                q, q_t = self.state
                image, dist = cam.capture(q)
                done = time.monotonic_ns()
                self.renders = cam.renders
                blur = self.spec.lens.coc_px(dist)
                frame = Frame(q_t or t_render, image, dist, blur, done - t_render)
                self.buffer.add(frame)
                self.on_frame(frame)
                window.append(done)
                if len(window) > 20:
                    del window[0]
                if len(window) > 1:
                    self.frames_per_s = (len(window) - 1) / ((window[-1] - window[0]) / 1e9)
                n += 1
                wait = t0 + n * period - time.monotonic_ns()
                if wait < 0:
                    self.late += 1
                    skipped = int(-wait // period) + 1  # keep to the grid: no burst to catch up
                    n += skipped
                    wait += skipped * period
                self._stop.wait(wait / 1e9)
        finally:
            cam.close()


@dataclass(slots=True)
class VisionCounters(Counters):
    measurements: int = 0
    not_found: int = 0  # measurements that found no target
    waited: int = 0  # measurements that waited for a frame newer than their request


class Vision:
    """The camera's buffer and the requests on it: measure (sharpness at an instant) and info."""

    def __init__(
        self, v: VisionConfig, robot: RobotConfig, publish: Callable[[vision_pb2.VisionReply], None]
    ) -> None:
        self.v, self.robot, self.publish = v, robot, publish
        self.buffer = FrameBuffer(v.buffer)
        self.acq = Acquisition(camera_spec(v), np.array(robot.q0), v.fps, self.buffer, robot.model)
        self.new_frame = asyncio.Event()
        self.counters = VisionCounters()

    async def frame_for(self, t_ns: int) -> Frame:
        newest = self.buffer.newest()
        if newest is None or newest.t_ns < t_ns:
            self.counters.waited += 1
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(WAIT_PERIODS / self.v.fps):
                    while (newest := self.buffer.newest()) is None or newest.t_ns < t_ns:
                        self.new_frame.clear()
                        await self.new_frame.wait()
        frame = self.buffer.closest(t_ns)
        if frame is None:
            raise RpcFault(FaultCode.NO_FRAME, "the camera has not taken a picture yet")
        return frame

    async def measure(self, req: vision_pb2.VisionRequest) -> vision_pb2.VisionReply:
        want = req.t_ns or time.monotonic_ns()
        frame = await self.frame_for(want)
        t = time.perf_counter_ns()
        res = sharpness.sharpness(frame.image)
        took = time.perf_counter_ns() - t
        self.counters.measurements += 1
        self.counters.not_found += not res.found
        reply = vision_pb2.VisionReply(
            id=req.id,
            found=res.found,
            sharpness=res.sharpness,
            reason=res.reason,
            frame_t_ns=frame.t_ns,
            request_t_ns=want,
            processed_ns=took,
            roi=list(res.roi),
            truth_distance_mm=frame.truth_distance_mm,
        )
        self.publish(reply)
        return reply

    def info(self, _req: vision_pb2.VisionInfoRequest) -> vision_pb2.CameraInfo:
        v = self.v
        return vision_pb2.CameraInfo(
            robot=self.robot.name,
            position_m=v.position_m,
            axis=v.axis,
            focal_mm=v.focal_mm,
            f_number=v.f_number,
            focus_mm=v.focus_mm,
            fps=v.fps,
            width_px=v.width_px,
            height_px=v.height_px,
            frames_per_s=self.acq.frames_per_s,
        )

    def report(self) -> dict[str, float]:
        out = self.counters.as_dict()
        out["frames"] = float(self.buffer.added)
        out["frames_per_s"] = self.acq.frames_per_s
        out["late_frames"] = float(self.acq.late)
        out["renders"] = float(self.acq.renders)
        return out
