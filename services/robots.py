"""Service `robots`: the cell's UR5e-class arms, emulated (MuJoCo or kinematic), over UDP.

Every robot streams its joints' status from its own UDP socket to the data
plane's address ([dataplane] listen; on XDP, its port on the switch's end of the
veth pair) and takes velocity commands on that socket.  On the bus:
announce/robot/<name> (plug and play: id, limits, UDP address) at start and
every ANNOUNCE_S, truth/<name> (ground truth) at truth_hz, and
events/robot/<name> for protective stops and resumes.

Stops and resumes come on the robots' own Responsive Link node, read between
ticks: an emergency stop (or a lost beacon) halts the drives at once, a stop
leaves them to the data plane's stop ramp; either way each robot reports
STATE STILL to the hub once it stands, and RESUMED when released.

Method robot/<name>.silence (SilenceRequest) is fault injection for `cell chaos`:
the robot stops answering for a while (no status, deaf to commands), as with its
cable pulled.  The robots tick from the start, bus or no bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Iterable

from cell import meter
from cell.bus import FaultCode, RpcFault
from cell.bus.node import Handler
from cell.robot.emulator import PYTHON_TICK_PRIORITY, RobotGroup
from cell.robot.node import (
    ANNOUNCE_S,
    ANNOUNCE_SLICE,
    Publisher,
    RobotsNode,
    announcement,
    build_emulated_controllers,
    build_groups,
    counters,
    has_node,
    robot_states,
)
from cell.service import ServiceContext, ServiceSpec
from cell.ur.remote import Daemon
from cell.ur.server import URInterfaces
from cell.v1 import robot_pb2

log = logging.getLogger("cell.robots")

DAEMONS_UP_S = 5.0  # the service waits this long at most for its daemons' programs to run


async def run(ctx: ServiceContext) -> None:
    groups = build_groups(ctx.config, ctx.bus.publish)
    # the UR controllers emulated for robots of backend "ur" (ur_emulate): not robots of the cell
    # themselves (their daemons are), so nothing of theirs goes on the bus but the daemons' view
    hidden: list[RobotGroup] = []
    try:
        hidden = build_emulated_controllers(ctx.config)
        node = RobotsNode(groups, ctx.config) if has_node(ctx.config) else None
    except BaseException:
        for g in [*groups, *hidden]:
            g.close()
        raise
    daemons = [g for g in groups if isinstance(g, Daemon)]
    urs: list[URInterfaces] = []
    dataplane = ctx.config.dataplane.address  # (derived: ~30 us, once, not per announcement)
    try:

        async def announce() -> None:
            """Every robot every ANNOUNCE_S, ANNOUNCE_SLICE at a time spread over the period: a fleet's
            thousand announcements at once were a 0.1-0.2 s step of every listener's loop (the data
            plane's, the controller's) every period."""
            rows = [(g, row) for g in groups for row in range(g.n)]
            parts = [rows[i : i + ANNOUNCE_SLICE] for i in range(0, len(rows), ANNOUNCE_SLICE)] or [[]]
            while True:
                for part in parts:
                    for g, row in part:
                        msg = announcement(g, row, dataplane)
                        ctx.bus.publish(f"announce/robot/{msg.name}", msg)
                    await asyncio.sleep(ANNOUNCE_S / len(parts))

        async def report() -> None:
            while True:
                ctx.counters.update(counters(groups))
                ctx.counters.update(robot_states(groups))
                for u in urs:
                    ctx.counters.update(u.report())
                if daemons:
                    ctx.counters.update(_sum(d.report() for d in daemons))
                if node is not None:
                    ctx.counters.update(node.counters())
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)

        def silencer(g: RobotGroup, rid: int, name: str) -> Handler:
            def silence(req: robot_pb2.SilenceRequest) -> robot_pb2.SilenceReply:
                if req.robot not in ("", name):
                    raise RpcFault(FaultCode.BAD_REQUEST, f"this is robot {name}, not {req.robot!r}")
                if not 0 < req.seconds <= 60:
                    raise RpcFault(FaultCode.BAD_REQUEST, f"seconds must be in (0, 60], got {req.seconds}")
                g.silence(rid, req.seconds)
                ctx.log.warning("fault injected: robot %s silent for %.1f s", name, req.seconds)
                return robot_pb2.SilenceReply(until_ns=time.monotonic_ns() + int(req.seconds * 1e9))

            return silence

        def announcer(g: RobotGroup, row: int) -> Handler:
            def announce(_req: robot_pb2.AnnounceRequest) -> robot_pb2.RobotAnnounce:
                return announcement(g, row, dataplane)

            return announce

        async def control() -> None:  # (after the packet path is running: it never waits for the bus)
            for g in groups:  # each robot answers where it lives (hosts may split the cell's robots)
                for row, r in enumerate(g.robots):
                    methods = {
                        "silence": (robot_pb2.SilenceRequest, silencer(g, r.id, r.name)),
                        "announce": (robot_pb2.AnnounceRequest, announcer(g, row)),
                    }
                    await ctx.bus.serve(f"robot/{r.name}", methods)

        for g in groups:  # (each emulated arm's UR interfaces: RTDE, dashboard, URScript)
            if ctx.config.ur.interfaces and not isinstance(g, Daemon):
                urs.append(URInterfaces(g, ctx.config, ctx.bus.publish))
                await urs[-1].start()
        for g in hidden:  # (offered whatever [ur] interfaces says: they are all these arms have)
            urs.append(URInterfaces(g, ctx.config))
            await urs[-1].start()
        ur_of = {id(u.group): u for u in urs}

        # groups that tick on timers, their grids staggered over the period: each group's tick has the
        # process to itself (on one grid a second group ticked as late as the first took: a UR5e and
        # a UR10e, two groups, had the robots' lateness p99 at 740 us where one group has 170)
        # the C threads take the process's real-time priority for themselves; where a group ticks in
        # Python here (a daemon's tick is its controller's RTDE package: it must stay real-time) the
        # rest of the process becomes real-time too, under every native loop (the robots' and the data
        # plane's: at 70 it held the data plane's thread up to 39 ms in a chaos campaign)
        if any(g.native is None for g in [*groups, *hidden]):
            for problem in meter.real_time_loop(PYTHON_TICK_PRIORITY):
                log.warning("%s", problem)
        ticking = [g for g in [*groups, *hidden] if not isinstance(g, Daemon)]
        t0 = time.monotonic_ns() + 2_000_000
        starts = {id(g): t0 + round(k * g.period * 1e9 / len(ticking)) for k, g in enumerate(ticking)}
        async with asyncio.TaskGroup() as tg:
            for g in groups:
                tick = Publisher(ctx.bus, g, node, ur_of.get(id(g)), full_rate=bool(ctx.config.recorder.bag))
                tg.create_task(g.run(tick, starts.get(id(g))), name=f"robots:{g.robots[0].backend}")
            for g in hidden:
                tg.create_task(g.run(ur_of[id(g)].after_tick, starts[id(g)]), name="robots:emulated-ur")
            tg.create_task(control(), name="control")
            if node is not None:
                tg.create_task(node.run(), name="rlink")
            tg.create_task(announce(), name="announce")
            tg.create_task(report(), name="report")
            if daemons:  # (ready once the daemons drive their arms, or say why not: never a hang)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(DAEMONS_UP_S):
                        await asyncio.gather(*(d.up.wait() for d in daemons))
                for d in daemons:
                    if not d.up.is_set():
                        ctx.log.warning("robot %s is not driven yet: %s", d.robots[0].name, d.why)
            ctx.ready()
    finally:
        for u in urs:
            u.close()
        if node is not None:
            node.close()
        for g in [*groups, *hidden]:
            g.close()


def _sum(reports: Iterable[dict[str, float]]) -> dict[str, float]:
    """Several daemons' figures as one: counts added, gauges and percentiles the worst of them."""
    out: dict[str, float] = {}
    for rep in reports:
        for k, v in rep.items():
            worst = k.endswith(("_p50", "_p99", "_max"))
            out[k] = max(out.get(k, v), v) if worst else out.get(k, 0.0) + v
    return out


SERVICE = ServiceSpec(
    name="robots",
    run=run,
    description="UR5e-class robot emulators (MuJoCo or kinematic) streaming joint status over UDP",
    ready_on_start=False,
)
