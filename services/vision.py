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

import cv2
import numpy as np

from cell.service import ServiceContext, ServiceSpec
from cell.v1 import robot_pb2, vision_pb2
from cell.vision.acquisition import Vision
from cell.vision.frames import Frame


async def run(ctx: ServiceContext) -> None:
    v = ctx.config.vision
    robot = ctx.config.robot(v.robot) if v.robot else ctx.config.robots[0]
    vision = Vision(v, robot, lambda reply: ctx.bus.publish("vision/measurement", reply))
    loop = asyncio.get_running_loop()
    images = {"n": 0}

    def on_frame(frame: Frame) -> None:  # in the camera thread
        loop.call_soon_threadsafe(vision.new_frame.set)
        if v.rerun_every and images["n"] % v.rerun_every == 0:
            ok, jpeg = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, 80])
            if ok:
                msg = vision_pb2.VisionImage(
                    t_ns=frame.t_ns, jpeg=jpeg.tobytes(), width_px=v.width_px, height_px=v.height_px
                )
                loop.call_soon_threadsafe(ctx.bus.publish, "vision/image", msg)
        images["n"] += 1

    vision.acq.on_frame = on_frame
    await asyncio.to_thread(vision.acq.start)
    try:
        await ctx.bus.serve(
            "vision",
            {
                "measure": (vision_pb2.VisionRequest, vision.measure),
                "info": (vision_pb2.VisionInfoRequest, vision.info),
            },
        )
        truth = await ctx.bus.subscribe(f"truth/{robot.name}")

        async def follow() -> None:
            while True:
                for m in await truth.recv_messages(robot_pb2.RobotTruth):
                    if m.robot_id == robot.id:  # (the topic is a prefix: truth/r1 is also truth/r10's)
                        vision.acq.state = (np.array(m.q), m.t_ns)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(follow(), name="vision-truth")
            ctx.ready()
            while True:
                ctx.counters.update(vision.report())
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)
    finally:
        await asyncio.to_thread(vision.acq.stop)


SERVICE = ServiceSpec(
    name="vision",
    run=run,
    description="a simulated close-range camera, its frame buffer and the sharpness pipeline (Adept paper)",
    ready_on_start=False,
)
