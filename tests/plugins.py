"""Services the tests add through [services.plugins]: real services run by the real runtime."""

from __future__ import annotations

import asyncio

from cell.service import ServiceContext, ServiceSpec
from cell.v1 import bus_pb2


async def _echo(ctx: ServiceContext) -> None:
    """Answers echo.echo with its request, and republishes test/in/X on test/out/X; ready (health
    ok) only once both are live, so a test that waits for ok never races the subscriptions."""

    def handle(req: bus_pb2.BenchPayload) -> bus_pb2.BenchPayload:
        ctx.counters["echo.requests"] = ctx.counters.get("echo.requests", 0) + 1
        return req

    await ctx.bus.serve("echo", {"echo": (bus_pb2.BenchPayload, handle)})
    sub = await ctx.bus.subscribe("test/in/")
    ctx.ready()
    while True:
        for env in await sub.recv_batch():
            ctx.bus.publish(
                "test/out/" + env.topic.removeprefix("test/in/"), env.decode(bus_pb2.BenchPayload)
            )
            ctx.counters["echo.republished"] = ctx.counters.get("echo.republished", 0) + 1


echo = ServiceSpec("echo", _echo, "echo requests and test/in/ messages", ready_on_start=False)


async def crasher(ctx: ServiceContext) -> None:
    """Runs briefly, then fails: for the supervision tests."""
    await asyncio.sleep(0.05)
    raise RuntimeError("deliberate failure from the crasher test service")


def doubles(x: int, out) -> None:
    """A benchmark's child (cell.bench.ur._in_process) that answers."""
    out.put(2 * x)


def dies(x: int, out) -> None:
    """One that ends with no answer, as a client that crashed would."""
    import os

    os._exit(3)
