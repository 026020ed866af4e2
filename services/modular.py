"""Service `modular`: the modular robot of seed 002 (cell.modular.robot) on the wall clock.

Its 1 ms [A, B, C, D] cycles run on a grid of the monotonic clock: each wake-up runs every cycle
that is due (a cycle run more than one cycle after its time is counted late), so the arm's time
is the cell's.  Requests (proto/cell/v1/modular.proto): `modular.move` (answered when the motion
ends, with its tool error), `modular.plug` / `modular.unplug` (a module on or off the network),
`modular.status`.  `modular/state` carries the arm and its cycle for Rerun at [modular] publish_hz;
the counters carry each module's state for `cell status`.
"""

from __future__ import annotations

import asyncio
import os
import time

import numpy as np

from cell.bus import FaultCode, RpcFault
from cell.modular.messages import state, status
from cell.modular.processes import CycleRobot
from cell.modular.reference import CYCLE_NS
from cell.modular.robot import ArmRobot, Ended, ModularRobot, MotionRefused
from cell.modular.wire import SnpLink
from cell.service import ServiceContext, ServiceSpec
from cell.v1 import modular_pb2 as pb

CATCH_UP = 50  # cycles run in one wake-up at most (a longer stall: the arm's time falls behind)


async def run(ctx: ServiceContext) -> None:
    c = ctx.config.modular
    link = SnpLink() if c.transport == "snp" else None
    robot: ArmRobot
    if c.transport == "cycle":
        # (two processes of its own; they poll without sleeping through each cycle's exchanges only
        # where this process may run on two cores: on one, a spinning one keeps the other out)
        robot = CycleRobot(
            np.array(c.q0), where=tuple(c.where), adapt=c.adapt, suspect_cycles=c.suspect_cycles,
            lost_cycles=c.lost_cycles, spin=len(os.sched_getaffinity(0)) >= 2, routed=c.network == "routed",
        )  # fmt: skip
        where = "C" if robot.native else "Python"
        ctx.log.info("modular robot: the SnP cycle's master and modules in processes of their own, "
                     "%g ms cycles in %s, %s links", robot.period_ns / 1e6, where, c.network)  # fmt: skip
    else:
        robot = ModularRobot(
            np.array(c.q0), loss=c.loss, where=tuple(c.where), adapt=c.adapt,
            suspect_cycles=c.suspect_cycles, lost_cycles=c.lost_cycles, link=link,
        )  # fmt: skip
    if link is not None:
        ctx.log.info("modular robot: its messages as SnP-MrT packets, master on udp %s:%d",
                     *link.master.getsockname())  # fmt: skip
    try:
        await _run(ctx, robot, link)
    finally:
        robot.close()
        if link is not None:
            link.close()


async def _run(ctx: ServiceContext, robot: ArmRobot, link: SnpLink | None) -> None:
    c = ctx.config.modular
    for path in ("pick-and-place", "circle"):  # (their IK before the cycles start, not in one)
        await asyncio.to_thread(robot.named, path)
    waiting: list[asyncio.Future[Ended]] = []  # the motion under way's requester (one at a time)
    late = 0

    async def move(req: pb.ModularMoveRequest) -> pb.ModularMoveReply:
        try:
            robot.move(
                joints=list(req.joints), tool=list(req.tool), path=req.path, speed=req.speed or c.speed_rad_s
            )
        except MotionRefused as exc:
            raise RpcFault(FaultCode.REFUSED, str(exc)) from None
        # (the robot holds the motion; its end comes from the clock's loop below)
        waiting.append(asyncio.get_running_loop().create_future())
        e = await waiting[-1]
        if e.failed:
            raise RpcFault(FaultCode.STOPPED, e.failed)
        return pb.ModularMoveReply(
            path=e.path, duration_s=e.cycles * CYCLE_NS / 1e9, tool_error_mm_max=e.tool_error_mm_max,
            tool_error_mm_rms=e.tool_error_mm_rms, guessed=e.guessed, cycles=e.cycles,
        )  # fmt: skip

    def plugging(plug: bool):
        def handle(req: pb.ModularModuleRequest) -> pb.ModularStatus:
            try:
                (robot.plug if plug else robot.unplug)(req.module)
            except MotionRefused as exc:
                raise RpcFault(FaultCode.UNKNOWN_MODULE, str(exc)) from None
            ctx.log.info("module %s %s", req.module, "plugged in" if plug else "unplugged")
            return status(robot, late)

        return handle

    await ctx.bus.serve(
        "modular",
        {
            "move": (pb.ModularMoveRequest, move),
            "plug": (pb.ModularModuleRequest, plugging(True)),
            "unplug": (pb.ModularModuleRequest, plugging(False)),
            "status": (pb.ModularStatusRequest, lambda _req: status(robot, late)),
        },
    )
    every = max(1, round(1e9 / c.publish_hz / CYCLE_NS))  # cycles between two modular/state

    def publish() -> None:
        ctx.bus.publish("modular/state", state(robot, late))

    ctx.ready()
    t0 = time.monotonic_ns()
    done = 0
    next_report = 0
    while True:
        now = time.monotonic_ns()
        due = (now - t0) // CYCLE_NS + 1
        if due - done > CATCH_UP:  # stalled: the arm's time falls behind the clock's
            late += due - done - CATCH_UP
            t0 += (due - done - CATCH_UP) * CYCLE_NS
            due = done + CATCH_UP
        late += max(0, due - done - 1)  # (every cycle but the newest ran after its time)
        while done < due:
            ended = robot.cycle()
            done += 1
            if ended is not None:
                for fut in waiting:
                    if not fut.done():  # (its requester may have gone)
                        fut.set_result(ended)
                waiting.clear()
            if done % every == 0:
                publish()
        if robot.failed:  # (its motion's requester told above: the supervisor restarts the service)
            raise RuntimeError(f"the modular robot: {robot.failed}")
        if now >= next_report:
            ctx.counters.update(robot.counters())
            ctx.counters["modular.late_cycles"] = late
            if link is not None:
                ctx.counters.update(link.report())
            next_report = now + int(ctx.config.services.heartbeat_s / 2 * 1e9)
        await asyncio.sleep(max(0, t0 + done * CYCLE_NS - time.monotonic_ns()) / 1e9)


SERVICE = ServiceSpec(
    name="modular",
    run=run,
    description="the modular robot (seed 002): six joint modules under VDC, 1 ms cycles, in MuJoCo",
    ready_on_start=False,
)
