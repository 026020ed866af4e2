"""Service `skills`: one AdeptServer-style TCP skill server per robot (its `skill_port`).

Clients send `<id>:<skill>[:<args>]\\r\\n` command messages (cell.skills.protocol)
and get one reply each.  Commands for one robot run in arrival order, across
all its connections.  Semantics as on the V+ controller:

- a motion (move_to, move_rel_world, move_rel_tool, move_joints,
  move_rel_joints) is answered once it is planned, loaded into the data plane
  and started; a motion sent while another runs starts when that one ends
  (no blending);
- `break` is answered when the robot has arrived (every joint within
  [skills] break_tolerance_rad of the goal) with the measured tool pose;
- `set_speed:N` applies to the next motion only, as V+'s SPEED without
  ALWAYS does (then 100% again);
- `enable_air` / `disable_air` set the vacuum valve, published on the bus;
- `estop[:<robot>,...]` (new) is an emergency stop over the Responsive Link of
  this server's robot, the robots named, or `all`: it is sent the moment it is
  read, ahead of the robot's queue, and answered once every named robot
  stands still; `resume[:...]` releases them.  Until then motions are
  answered `error:stopped`.

Replies: `done` with the seconds since the server started at which the
command's turn came and at which it was answered, and a tool pose (the
motion's end for a motion, the measured one for `break`, and for the rest the
latest the server holds from the robot's state broadcast, `truth/<robot>`, at
most one broadcast period old plus the bus's delivery; the controller's if the
broadcast is off or stalled); or `error` with a code.  Every command's life
goes on the bus (skills/<robot>/trace) for Gantt charts and timing figures.
"""

from __future__ import annotations

import asyncio
import contextlib
import time

from cell.rlink.client import EventClient
from cell.service import ServiceContext, ServiceSpec
from cell.skills.server import RobotSkills
from cell.v1 import robot_pb2


async def run(ctx: ServiceContext) -> None:
    t0 = time.monotonic_ns()
    async with contextlib.AsyncExitStack() as stack, asyncio.TaskGroup() as tg:
        link = await stack.enter_async_context(EventClient(ctx.config))
        servers = [RobotSkills(r, ctx.config, ctx.bus, t0, link) for r in ctx.config.robots]
        for s in servers:
            server = await asyncio.start_server(
                s.serve_connection, ctx.config.skills.host, s.robot.skill_port, reuse_address=True
            )
            await stack.enter_async_context(server)
            tg.create_task(s.run_queue(), name=f"skills-{s.robot.name}")
        ctx.log.info(
            "skill servers: %s",
            ", ".join(f"{s.robot.name} on {ctx.config.skills.host}:{s.robot.skill_port}" for s in servers),
        )
        by_id = {s.robot.id: s for s in servers}
        truth = await ctx.bus.subscribe("truth/")

        async def follow_truth() -> None:
            while True:
                for m in await truth.recv_messages(robot_pb2.RobotTruth):
                    if (s := by_id.get(m.robot_id)) is not None:
                        s.held = m

        tg.create_task(follow_truth(), name="skills-truth")
        # (a controller that dies mid-motion: what waits on it ends at once on its supervisor's
        # event, cell.bus.ServiceDown; the server answers those commands `stopped`)
        ctx.ready()

        async def report() -> None:
            while True:
                for s in servers:
                    ctx.counters.update(s.counters.as_dict(f"{s.robot.name}."))
                await asyncio.sleep(ctx.config.services.heartbeat_s / 2)  # (twice a heartbeat)

        tg.create_task(report())


SERVICE = ServiceSpec(
    name="skills",
    run=run,
    description="AdeptServer-style TCP skill servers, one per robot (ASCII command messages)",
    ready_on_start=False,
)
