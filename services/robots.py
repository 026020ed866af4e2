"""Service `robots`: the cell's UR5e-class arms, emulated (MuJoCo or kinematic), over UDP.

Every robot streams its joints' status from its own UDP socket to
[dataplane] listen and takes velocity commands on that socket.  On the bus:
announce/robot/<name> (plug and play: id, limits, UDP address) at start and
every ANNOUNCE_S, truth/<name> (ground truth) at truth_hz, and
events/robot/<name> for protective stops and resumes.
"""

from __future__ import annotations

import asyncio
import time
from collections import defaultdict

import numpy as np

from cell.bus import Bus
from cell.config import CellConfig, RobotConfig, parse_host_port
from cell.robot.emulator import RobotGroup
from cell.service import ServiceContext, ServiceSpec
from cell.v1 import robot_pb2

ANNOUNCE_S = 2.0


def build_groups(config: CellConfig) -> list[RobotGroup]:
    """One group per (backend, model, rates); robots bind the data plane's host."""
    by_key: dict[tuple, list[RobotConfig]] = defaultdict(list)
    for r in config.robots:
        by_key[(r.backend, r.model, r.status_hz, r.command_hz)].append(r)
    host, _ = parse_host_port(config.dataplane.listen)
    groups: list[RobotGroup] = []
    try:
        groups.extend(RobotGroup(robots, config.dataplane.listen, host=host) for robots in by_key.values())
    except BaseException:
        for g in groups:
            g.close()
        raise
    return groups


def announcements(group: RobotGroup, dataplane: str) -> list[robot_pb2.RobotAnnounce]:
    lim = group.arm.limits
    return [
        robot_pb2.RobotAnnounce(
            robot_id=r.id,
            name=r.name,
            model=r.model,
            backend=r.backend,
            joints=group.dof,
            q_min=lim.q_min,
            q_max=lim.q_max,
            v_max=lim.v_max,
            a_max=lim.a_max,
            udp_address=addr,
            status_hz=r.status_hz,
            command_hz=r.command_hz,
            dataplane=dataplane,
        )
        for r, addr in zip(group.robots, group.addresses(), strict=True)
    ]


class Publisher:
    """What one group tells the bus after each tick."""

    def __init__(self, bus: Bus, group: RobotGroup) -> None:
        self.bus = bus
        hz = group.robots[0].truth_hz
        self.every = max(1, round(group.robots[0].status_hz / hz)) if hz > 0 else 0
        self.names = [r.name for r in group.robots]

    def __call__(self, group: RobotGroup, stopping: np.ndarray, resuming: np.ndarray) -> None:
        now = time.monotonic_ns()
        for rows, kind, text in (
            (stopping, robot_pb2.RobotEvent.KIND_PROTECTIVE_STOP, "no command for the watchdog's windows"),
            (resuming, robot_pb2.RobotEvent.KIND_RESUMED, "commands resumed"),
        ):
            for row in rows:
                r = group.robots[row]
                ev = robot_pb2.RobotEvent(robot_id=r.id, name=r.name, kind=kind, text=text, t_ns=now)
                self.bus.publish(f"events/robot/{r.name}", ev)
        if self.every and group.tick_no % self.every == 0:
            b = group.backend
            at = round(group.state_time * 1e9)  # CLOCK_MONOTONIC ns of the state, not of publishing
            for row, name in enumerate(self.names):
                q = b.q[row]
                self.bus.publish(
                    f"truth/{name}",
                    robot_pb2.RobotTruth(
                        robot_id=int(group.ids[row]),
                        t_ns=at,
                        q=q,
                        qd=b.qd[row],
                        tool_pose=group.arm.tool_pose(q),
                        target=group.drives.target[row],
                        stopped=bool(group.drives.stopped[row]),
                        tick=group.tick_no,
                    ),
                )


def counters(groups: list[RobotGroup]) -> dict[str, float]:
    total: dict[str, float] = defaultdict(float)
    for g in groups:
        for k, v in g.counters.as_dict().items():
            total[k] = max(total[k], v) if k.startswith("lateness") else total[k] + v
    total["robots"] = sum(g.n for g in groups)
    return dict(total)


async def run(ctx: ServiceContext) -> None:
    groups = build_groups(ctx.config)
    try:

        async def announce() -> None:
            while True:
                for g in groups:
                    for msg in announcements(g, ctx.config.dataplane.listen):
                        ctx.bus.publish(f"announce/robot/{msg.name}", msg)
                await asyncio.sleep(ANNOUNCE_S)

        async def report() -> None:
            while True:
                ctx.counters.update(counters(groups))
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)

        async with asyncio.TaskGroup() as tg:
            for g in groups:
                tg.create_task(g.run(Publisher(ctx.bus, g)), name=f"robots:{g.robots[0].backend}")
            tg.create_task(announce(), name="announce")
            tg.create_task(report(), name="report")
            ctx.ready()
    finally:
        for g in groups:
            g.close()


SERVICE = ServiceSpec(
    name="robots",
    run=run,
    description="UR5e-class robot emulators (MuJoCo or kinematic) streaming joint status over UDP",
    ready_on_start=False,
)
