"""Service `dataplane`: the in-network velocity controller (NSDI'22) as a data plane.

The packet path is cell.dataplane.plane's (numpy, native C, or the XDP program); this
service serves its control plane on the bus (service "dataplane", methods
"update" (TableUpdate, atomic), "merge", "state", "load_constants"), adds
robots as they announce themselves (announce/robot/<name>) and publishes
telemetry on dataplane/counters once a second.
"""

from __future__ import annotations

import asyncio
import contextlib

from cell.bus import BusError
from cell.dataplane.backends import BACKENDS
from cell.dataplane.plane import DataPlane, PlaneNode
from cell.dataplane.tables import NO_ROW
from cell.native import NativeUnavailable
from cell.service import ServiceContext, ServiceSpec
from cell.v1 import dataplane_pb2, robot_pb2


async def run(ctx: ServiceContext) -> None:
    backend, why = ctx.config.dataplane.chosen()
    try:
        plane = BACKENDS[backend]()(ctx.config)
    except NativeUnavailable as exc:  # (auto or not, a data plane that cannot be built: say so, run numpy)
        ctx.log.warning("the %s data plane cannot run here (%s): the numpy one runs instead", backend, exc)
        backend, why, plane = "numpy", f"{backend} unavailable: {exc}", DataPlane(ctx.config)
    ctx.log.info("data plane backend: %s (%s)", backend, why)
    try:
        events = PlaneNode(plane, ctx.config)
    except BaseException:
        plane.close()
        raise
    try:
        bus = ctx.bus

        async def control() -> None:
            """The control plane on the bus; the packet path runs meanwhile, bus or no bus."""
            await bus.serve(
                "dataplane",
                {
                    "update": (dataplane_pb2.TableUpdate, plane.update),
                    "merge": (dataplane_pb2.MergeRequest, plane.merge),
                    "state": (dataplane_pb2.StateRequest, plane.state),
                    "load_constants": (dataplane_pb2.Constants, plane.load_constants),
                },
            )
            announcements = await bus.subscribe("announce/robot/")
            ctx.ready()
            async for msg in announcements.messages(robot_pb2.RobotAnnounce):
                if plane.tables.robot_entity[msg.robot_id] == NO_ROW:
                    plane.add_robot(msg.robot_id, msg.joints)
                    events.add_robot(msg.robot_id)
                    ctx.log.info("robot %s (id %d) joined", msg.name, msg.robot_id)

        async def held() -> None:
            """Robots the Responsive Link's hub holds stopped (an e-stop this process, restarted, did not
            see): REG_stop set again.  No hub answering (a fresh start): nothing is held."""
            if not ctx.config.runs("rlink"):
                return
            with contextlib.suppress(BusError, TimeoutError):
                reply = await bus.request("rlink", "held", robot_pb2.HeldRequest(), robot_pb2.HeldReply)
                if reply.robot_ids:
                    events.restore(list(reply.robot_ids), list(reply.emergency))
                    ctx.log.warning("robots %s are held stopped by the Responsive Link: REG_stop set again",
                                    list(reply.robot_ids))  # fmt: skip

        async def telemetry() -> None:
            while True:
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)  # (twice a heartbeat)
                state = plane.state(with_robots=False)
                state.counters.update(events.counters())
                ctx.counters.update(state.counters)
                bus.publish("dataplane/counters", state)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(plane.run(), name="packets")
            tg.create_task(plane.sweep(), name="sweep")
            tg.create_task(plane.pump(), name="egress")
            tg.create_task(events.run(), name="events")
            tg.create_task(control(), name="control")
            tg.create_task(telemetry(), name="telemetry")
            tg.create_task(held(), name="held")
    finally:
        plane.close()
        events.close()


SERVICE = ServiceSpec(
    name="dataplane",
    run=run,
    description="in-network velocity controller: status datagrams in, velocity commands out, at line rate",
    ready_on_start=False,
)
