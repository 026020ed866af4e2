"""Service `recorder`: the cell's run drawn in Rerun (cell/recorder/live.py: live in a viewer, or into
an .rrd file) and/or written as a ROS 2 bag (cell/recorder/bag.py), as [recorder] says.

With mode = "off" and no bag (the default of `cell up`) it only says it is ready: Rerun (with
pyarrow, about 0.4 s of imports) and rosbags are loaded only when something is recorded.
"""

from __future__ import annotations

import asyncio

from cell.service import ServiceContext, ServiceSpec


async def run(ctx: ServiceContext) -> None:
    cfg = ctx.config.recorder
    parts = []
    if cfg.bag:
        from cell.recorder import bag

        parts.append(bag.record)
    if cfg.mode != "off":
        from cell.recorder import live

        parts.append(live.record)
    if not parts:
        ctx.ready()
        await asyncio.Event().wait()
    waiting = len(parts)

    def one_ready() -> None:  # ready once every part subscribed
        nonlocal waiting
        waiting -= 1
        if waiting == 0:
            ctx.ready()

    async with asyncio.TaskGroup() as tg:
        for part in parts:
            tg.create_task(part(ctx, one_ready))


SERVICE = ServiceSpec(
    name="recorder",
    run=run,
    description="records the run: Rerun (live viewer, web viewer, .rrd file) and/or a ROS 2 bag (MCAP)",
    ready_on_start=False,
)
