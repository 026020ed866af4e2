"""Service `snp`: the SnP handler (SpW-SnP-MR) on UDP [snp] listen.

Time-bounded queries about the cell's robots (SnP-MrT: answered before their
deadline or denied), time synchronisation (SnP-TSP: this service's clock is
the cell clock, CLOCK_REALTIME of its host) and PID management.  The values
come from the bus: ground truth (truth/<name>), the controller's plans
(plan/<name>), robots as they announce themselves.  Packet layout:
docs/protocols/snp-mrt.md.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np

from cell.config import parse_host_port
from cell.service import ServiceContext, ServiceSpec
from cell.snp.endpoint import HandlerEndpoint
from cell.snp.handler import Handler
from cell.snp.state import CellState
from cell.v1 import controller_pb2, robot_pb2, snp_pb2


async def run(ctx: ServiceContext) -> None:
    state = CellState()
    for r in ctx.config.robots:
        state.add_robot(r.id, 6)
    handler = Handler(state, time.time_ns)
    loop = asyncio.get_running_loop()
    host, port = parse_host_port(ctx.config.snp.listen)
    transport, _ = await loop.create_datagram_endpoint(
        lambda: HandlerEndpoint(handler), local_addr=(host, port)
    )
    try:
        bus = ctx.bus
        truth = await bus.subscribe("truth/")
        plans = await bus.subscribe("plan/")
        announce = await bus.subscribe("announce/robot/")

        async def follow_truth() -> None:
            while True:
                for m in await truth.recv_messages(robot_pb2.RobotTruth):
                    state.observe(m.robot_id, m.t_ns, np.array(m.q), np.array(m.qd), np.array(m.target))

        async def follow_plans() -> None:
            async for p in plans.messages(controller_pb2.Plan):
                n = p.joints
                pos = np.array(p.positions).reshape(-1, n)
                vel = np.array(p.velocities).reshape(-1, n)
                state.set_plan(p.robot_id, np.array(p.t_ns), pos, vel)

        async def follow_robots() -> None:
            async for a in announce.messages(robot_pb2.RobotAnnounce):
                state.add_robot(a.robot_id, a.joints)

        async def report() -> None:
            while True:
                while handler.denials:  # each denial on the bus, for viewers and logs
                    qid, why, peer = handler.denials.popleft()
                    denial = snp_pb2.SnpDenial(
                        query_id=qid, explanation=why, peer=str(peer), t_ns=time.monotonic_ns()
                    )
                    bus.publish("events/snp/denial", denial)
                ctx.counters.update(handler.counters.as_dict())
                ctx.counters["service_estimate_us"] = handler.service_ns / 1e3
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)  # (twice a heartbeat)

        async with asyncio.TaskGroup() as tg:
            for f in (follow_truth, follow_plans, follow_robots, report):
                tg.create_task(f(), name=f"snp-{f.__name__}")
            ctx.log.info("SnP handler on udp %s:%d", host, port)
            ctx.ready()
    finally:
        transport.close()


SERVICE = ServiceSpec(
    name="snp",
    run=run,
    description="SnP-MrT time-bounded query handler, SnP-TSP time sync, PID management (UDP)",
    ready_on_start=False,
)
