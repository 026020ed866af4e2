"""Service `rlink`: the hub of the cell's Responsive Link (cell.rlink.cellnet).

The hub routes events between its host interface (L0: `cell estop`, task
scripts, skill servers), the data plane's node (L1) and the robots' node (L2),
and sends the watchdog beacon to every node at [rlink] beacon_hz.  What passes
through its host it also tells the bus, after the fact, for the controller,
the recorder and `cell status`: events/robot/<name> (RobotEvent: e-stop, stop,
resume ordered; a robot standing still).  The stop itself never waits for the
bus.
"""

from __future__ import annotations

import asyncio

from cell.rlink.hub import Hub
from cell.service import ServiceContext, ServiceSpec
from cell.v1 import robot_pb2


async def run(ctx: ServiceContext) -> None:
    hub = Hub(ctx.config, ctx.bus)
    try:
        await ctx.bus.serve("rlink", {"held": (robot_pb2.HeldRequest, hub.held_reply)})
        async with asyncio.TaskGroup() as tg:
            tg.create_task(hub.link.run(), name="rlink")
            tg.create_task(hub.beacon(), name="beacon")
            ctx.ready()
            while True:
                ctx.counters.update(hub.report())
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)
    finally:
        hub.close()


SERVICE = ServiceSpec(
    name="rlink",
    run=run,
    description="Responsive Link hub: e-stop and state events to the data plane and robots, beacon",
    ready_on_start=False,
)
