"""Service `bus`: the forwarder every other node connects to (XSUB at bus.pub, XPUB at bus.sub)."""

from __future__ import annotations

import asyncio

from cell.bus import Forwarder
from cell.service import ServiceContext, ServiceSpec


async def run(ctx: ServiceContext) -> None:
    forwarder = Forwarder(ctx.config.bus)
    forwarder.start()
    try:
        ctx.log.info("forwarding %s -> %s", ctx.config.bus.pub, ctx.config.bus.sub)
        ctx.ready()
        while True:
            ctx.counters.update((await forwarder.statistics()).as_counters())
            ctx.counters.update(forwarder.counters())
            await asyncio.sleep(ctx.config.services.heartbeat_s / 2)
    finally:
        forwarder.stop()


SERVICE = ServiceSpec(
    name="bus",
    run=run,
    description="ZeroMQ XSUB/XPUB forwarder: the cell's message bus",
    needs_bus=False,
    ready_on_start=False,
)
