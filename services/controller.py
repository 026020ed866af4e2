"""Service `controller`: the industrial controller on the bus (service "controller").

Methods: move (MoveRequest: joints, a pose, or a straight line; absolute or relative to the
base or the tool; replies when the motion has ended, or with start_only once it has started;
a robot's motions run one after another in request order), arrive (until the robot stands at
the end of its motions: V+'s BREAK), stop (protective stop of some robots or
all), resume (re-plan an interrupted motion from where the robot stands), pose (where a robot
is, from its last status at the data plane).  Errors come back with codes: unknown_robot,
bad_request, unreachable, plan, stopped, busy.
"""

from __future__ import annotations

import asyncio

from cell.bus import BusError
from cell.controller.controller import Controller
from cell.controller.rpc import ControllerService
from cell.service import ServiceContext, ServiceSpec
from cell.v1 import controller_pb2, robot_pb2


async def run(ctx: ServiceContext) -> None:
    async with Controller(ctx.bus, ctx.config) as ctl:
        await serve(ctx, ControllerService(ctl))


async def serve(ctx: ServiceContext, svc: ControllerService) -> None:
    await ctx.bus.serve(
        "controller",
        {
            "move": (controller_pb2.MoveRequest, svc.move),
            "stop": (controller_pb2.StopRequest, svc.stop),
            "resume": (controller_pb2.RobotRequest, svc.resume),
            "pose": (controller_pb2.RobotRequest, svc.pose),
            "arrive": (controller_pb2.ArriveRequest, svc.arrive),
            "replan": (controller_pb2.MoveRequest, svc.replan),
            "move_together": (controller_pb2.MoveTogetherRequest, svc.move_together),
            "follow": (controller_pb2.FollowRequest, svc.follow),
            "name": (controller_pb2.NameRequest, svc.name),
            "prepare_alternates": (controller_pb2.AlternatesRequest, svc.prepare_alternates),
            "take_alternate": (controller_pb2.TakeAlternate, svc.take_alternate),
            "loop": (controller_pb2.LoopRequest, svc.loop),
            "end_loop": (controller_pb2.RobotRequest, svc.end_loop),
        },
    )
    ctl = svc.ctl
    events = await ctx.bus.subscribe("events/robot/")
    armings = await ctx.bus.subscribe("alternate/")

    async def follow_armings() -> None:
        """Alternates armed by an event on the bus (alternate/<robot>): taken as if requested."""

        async def take(ev: controller_pb2.TakeAlternate) -> None:
            try:
                await svc.take_alternate(ev)
                svc.counters.alternates_taken += 1
            except Exception as exc:  # (a bad event is the sender's: said, never fatal here)
                svc.counters.alternates_refused += 1
                ctx.log.warning("alternate %r of %r not taken: %s", ev.name, ev.robot, exc)

        async with asyncio.TaskGroup() as takes:  # (each returns when its branch ends: not inline)
            async for ev in armings.messages(controller_pb2.TakeAlternate):
                takes.create_task(take(ev))

    async def stopped_now(robot: int) -> bool:
        """Whether the data plane holds the robot stopped now.  The hub tells the bus after the fact,
        and a hub that hung tells it seconds late, after the robot's release and a new motion: the
        data plane, which every stop reaches first, is the one to ask (three times: one that is
        starting up answers within a second or two).  Unanswered: stopped."""
        for _ in range(3):
            try:
                st = await ctl.dp.state([robot], robots_only=True, timeout=0.5)
            except (BusError, TimeoutError):
                continue
            return not st.robots or st.robots[0].stopped
        return True

    async def follow_link() -> None:
        """Stops and releases over the Responsive Link, as the hub tells them after the fact, and URScript
        programs holding a robot, as its UR interfaces tell them.  A stop is checked with the data plane
        on the side (seconds when it hangs): the events behind it, a release first, are not held up."""
        RE = robot_pb2.RobotEvent
        # the hub's time of each robot's last stop or release: one older comes late (a hub's backlog
        # drained by the forwarder after its reconnection, behind the newer events), and is no order
        latest: dict[int, int] = {}

        async def stop(ev: robot_pb2.RobotEvent) -> None:
            held = await stopped_now(ev.robot_id)
            if latest.get(ev.robot_id) != ev.t_ns:
                return  # a newer stop or release came meanwhile: it rules (a real stop's drop is noted)
            if not held:
                svc.counters.stale_link_events += 1
                ctx.log.warning("robot %d: a stop came after its release (late): ignored", ev.robot_id)
                return
            await ctl.stopped_on_link(ev.robot_id)

        async with asyncio.TaskGroup() as checks:
            async for ev in events.messages(RE):
                if ev.kind in (RE.KIND_ESTOP, RE.KIND_STOP, RE.KIND_RESUME):
                    if ev.t_ns < latest.get(ev.robot_id, 0):
                        svc.counters.stale_link_events += 1
                        kind = RE.Kind.Name(ev.kind)
                        ctx.log.warning("an old %s of robot %d came late: ignored", kind, ev.robot_id)
                        continue
                    latest[ev.robot_id] = ev.t_ns
                if ev.kind in (RE.KIND_ESTOP, RE.KIND_STOP):
                    checks.create_task(stop(ev))
                elif ev.kind == RE.KIND_RESUME:
                    ctl.released_on_link(ev.robot_id)
                elif ev.kind == RE.KIND_PROGRAM:
                    await ctl.held_by_program(ev.robot_id, ev.text)
                elif ev.kind == RE.KIND_PROGRAM_END:
                    ctl.program_ended(ev.robot_id)

    async with asyncio.TaskGroup() as tg:
        tg.create_task(follow_link(), name="follow-link")
        tg.create_task(follow_armings(), name="follow-armings")
        tg.create_task(ctl.supervise(), name="supervise-dataplane")
        ctx.ready()
        while True:  # requests are served by the bus node's reader; this only reports
            ctx.counters.update(svc.report())
            await asyncio.sleep(ctx.config.services.heartbeat_s / 2)


SERVICE = ServiceSpec(
    name="controller",
    run=run,
    description="industrial controller: plans motions and streams them into the data plane's tables",
    ready_on_start=False,
)
