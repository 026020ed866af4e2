"""Service `vision`: the Adept paper's ImAcqService and ImProcNode on one simulated camera.

A thread of its own renders the camera's view ([vision], cell.vision.camera)
of the watched robot at its latest joint positions (the `truth/<robot>`
stream) at [vision] fps, into a circular buffer of recent frames stamped
with the instant of the robot state they show.  Requests over the bus:

- `vision.measure` (VisionRequest): the sharpness (Fig. 7) of the frame
  closest in time to the request's instant; if the newest frame is older
  than that instant, the next frame is waited for (at most two periods), so
  a request made after a motion never gets a picture from before it;
- `vision.info`: the camera's geometry, optics and measured frame rate.

Every measurement is published on `vision/measurement`, every n-th frame as
a JPEG on `vision/image` (the recorder draws both).  The camera renders in a
thread so that the bus and the requests stay responsive; the default config
runs the service in a process of its own, off the packet path's core.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time

import cv2
import numpy as np

from cell.bus import RpcFault
from cell.service import ServiceContext, ServiceSpec
from cell.v1 import robot_pb2, vision_pb2
from cell.vision import sharpness
from cell.vision.camera import Camera, CameraSpec
from cell.vision.frames import Frame, FrameBuffer
from cell.vision.optics import ThinLens

WAIT_PERIODS = 2  # a request for an instant newer than every frame waits at most this many frames


def camera_spec(ctx: ServiceContext) -> CameraSpec:
    v = ctx.config.vision
    lens = ThinLens(v.focal_mm, v.f_number, v.focus_mm, v.pixel_um)
    return CameraSpec(tuple(v.position_m), tuple(v.axis), v.width_px, v.height_px, lens, v.noise_dn)  # type: ignore[arg-type]


class Acquisition:
    """The camera thread: renders at the frame rate, on absolute deadlines, into the buffer."""

    def __init__(self, spec: CameraSpec, q0: np.ndarray, fps: float, buffer: FrameBuffer) -> None:
        self.spec, self.fps, self.buffer = spec, fps, buffer
        # the joint positions to render and their instant (0: none heard yet, q0), swapped as one
        self.state: tuple[np.ndarray, int] = (np.array(q0, float), 0)
        self.error: BaseException | None = None
        self.frames_per_s = 0.0
        self.late = 0
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
            cam = Camera(self.spec)
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


async def run(ctx: ServiceContext) -> None:
    v = ctx.config.vision
    robot = ctx.config.robot(v.robot) if v.robot else ctx.config.robots[0]
    spec = camera_spec(ctx)
    buffer = FrameBuffer(v.buffer)
    acq = Acquisition(spec, np.array(robot.q0), v.fps, buffer)
    loop = asyncio.get_running_loop()
    new_frame = asyncio.Event()
    images = {"n": 0}

    def on_frame(frame: Frame) -> None:  # in the camera thread
        loop.call_soon_threadsafe(new_frame.set)
        if v.rerun_every and images["n"] % v.rerun_every == 0:
            ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, 80])
            if ok:
                msg = vision_pb2.VisionImage(
                    t_ns=frame.t_ns, jpeg=jpeg.tobytes(), width_px=v.width_px, height_px=v.height_px
                )
                loop.call_soon_threadsafe(ctx.bus.publish, "vision/image", msg)
        images["n"] += 1

    acq.on_frame = on_frame
    await asyncio.to_thread(acq.start)
    counters = {"measurements": 0, "not_found": 0, "waited": 0}

    async def frame_for(t_ns: int) -> Frame:
        newest = buffer.newest()
        if newest is None or newest.t_ns < t_ns:
            counters["waited"] += 1
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(WAIT_PERIODS / v.fps):
                    while (newest := buffer.newest()) is None or newest.t_ns < t_ns:
                        new_frame.clear()
                        await new_frame.wait()
        frame = buffer.closest(t_ns)
        if frame is None:
            raise RpcFault("no_frame", "the camera has not taken a picture yet")
        return frame

    async def measure(req: vision_pb2.VisionRequest) -> vision_pb2.VisionReply:
        want = req.t_ns or time.monotonic_ns()
        frame = await frame_for(want)
        t = time.perf_counter_ns()
        res = sharpness.sharpness(frame.image)
        took = time.perf_counter_ns() - t
        counters["measurements"] += 1
        counters["not_found"] += not res.found
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
        ctx.bus.publish("vision/measurement", reply)
        return reply

    def info(_req: vision_pb2.VisionInfoRequest) -> vision_pb2.CameraInfo:
        return vision_pb2.CameraInfo(
            robot=robot.name,
            position_m=v.position_m,
            axis=v.axis,
            focal_mm=v.focal_mm,
            f_number=v.f_number,
            focus_mm=v.focus_mm,
            fps=v.fps,
            width_px=v.width_px,
            height_px=v.height_px,
            frames_per_s=acq.frames_per_s,
        )

    try:
        await ctx.bus.serve(
            "vision",
            {
                "measure": (vision_pb2.VisionRequest, measure),
                "info": (vision_pb2.VisionInfoRequest, info),
            },
        )
        truth = await ctx.bus.subscribe(f"truth/{robot.name}")

        async def follow() -> None:
            while True:
                for m in await truth.recv_messages(robot_pb2.RobotTruth):
                    if m.robot_id == robot.id:  # (the topic is a prefix: truth/r1 is also truth/r10's)
                        acq.state = (np.array(m.q), m.t_ns)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(follow(), name="vision-truth")
            ctx.ready()
            while True:
                ctx.counters.update({k: float(n) for k, n in counters.items()})
                ctx.counters["frames"] = float(buffer.added)
                ctx.counters["frames_per_s"] = acq.frames_per_s
                ctx.counters["late_frames"] = float(acq.late)
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)
    finally:
        await asyncio.to_thread(acq.stop)


SERVICE = ServiceSpec(
    name="vision",
    run=run,
    description="a simulated close-range camera, its frame buffer and the sharpness pipeline (Adept paper)",
    ready_on_start=False,
)
