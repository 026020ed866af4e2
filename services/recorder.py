"""Service `recorder`: the cell drawn in Rerun, live (spawn, serve) or into an .rrd file (save).

What it draws is cell/recorder/live.py.  With [recorder] mode = "off" (the
default of `cell up`) it only says it is ready: Rerun, with pyarrow about
0.4 s of imports, is loaded only when something is recorded.
"""

from __future__ import annotations

import asyncio

from cell.service import ServiceContext, ServiceSpec


async def run(ctx: ServiceContext) -> None:
    if ctx.config.recorder.mode == "off":
        ctx.ready()
        await asyncio.Event().wait()
    from cell.recorder.live import record

    await record(ctx)


SERVICE = ServiceSpec(
    name="recorder",
    run=run,
    description="draws the cell in Rerun (live viewer, web viewer, or an .rrd file)",
    ready_on_start=False,
)
