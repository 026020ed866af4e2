"""`cell follow SOURCE`: a trajectory planned elsewhere (JSON, CSV, a ROS 2 bag) run on a running cell."""

from __future__ import annotations

import argparse
import sys

from cell.commands import Command, config_arg, load, register


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="a .json or .csv file, or a ROS 2 bag (directory, .mcap or .db3)")
    config_arg(p)
    p.add_argument("--robot", metavar="R", help="the robot to run it on (when the source does not say)")
    p.add_argument("--topic", metavar="T", help="the bag's topic (when it has several of trajectories)")
    p.add_argument("--index", type=int, metavar="N", help="the bag's N-th message on it (default: the last)")
    p.add_argument(
        "--speed",
        type=float,
        default=50.0,
        metavar="PCT",
        help="the approach to the first point, and an untimed Cartesian path (default 50 %%)",
    )
    p.add_argument(
        "--name",
        metavar="NAME",
        help="do not run it: give it to the cell under NAME (checked now), for the skill servers' "
        "follow:NAME and task scripts; a name given again is replaced",
    )
    p.add_argument(
        "--max-speed",
        type=float,
        metavar="M_S",
        help="a Cartesian path whose poses have no times: the tool's top speed between them (m/s; "
        "default: its own, else as fast as ruckig times it within the joints' limits at --speed)",
    )
    p.add_argument(
        "--replace",
        action="store_true",
        help="a robot under way is switched onto it on the fly (one robot), not after its motion",
    )


def run(args: argparse.Namespace) -> int:
    from cell import aio
    from cell.trajectory.cartesian import Poses
    from cell.trajectory.model import TrajectoryError
    from cell.trajectory.sources import Points, split_robots
    from cell.trajectory.sources import load as load_source

    config = load(args)
    prefixes = {r.name: r.prefix for r in config.robots}
    try:
        found: list[Points | Poses] = []
        for pts in load_source(args.source, args.topic, args.index):
            # one trajectory of several robots' joints (a dual-arm group): one per robot, started together
            parts = split_robots(pts, prefixes) if isinstance(pts, Points) and not pts.robot else None
            found += parts or [pts]
    except TrajectoryError as exc:
        print(f"cell follow: {exc}", file=sys.stderr)
        return 2
    names = [r.name for r in config.robots]
    for pts in found:
        pts.robot = pts.robot or args.robot or (names[0] if len(names) == 1 else "")
        if not pts.robot:
            print(f"cell follow: robots {', '.join(names)}: say which with --robot", file=sys.stderr)
            return 2
        if pts.robot not in names:
            print(f"cell follow: no robot {pts.robot!r} in this cell ({', '.join(names)})", file=sys.stderr)
            return 2
        if isinstance(pts, Poses) and pts.t is None and args.max_speed is not None:
            pts.max_speed = args.max_speed  # (untimed, without one: timed by ruckig, joint_points())
    speed = args.speed / 100.0
    if args.name:
        return aio.run(_name(config, found, args.name, speed))
    return aio.run(_follow(config, found, args.speed, args.replace))


async def joint_points(bus, config, found: list, speed: float = 0.5) -> list:
    """Every source's trajectories as joint points: a Cartesian path (cell.trajectory.cartesian) is
    solved by IK from where its robot stands now (the controller says), one with neither times nor
    a tool speed timed by ruckig within the limits the controller plans with at `speed`;
    TrajectoryError if it cannot."""
    from cell.robot.arm import arm_model
    from cell.trajectory.cartesian import Poses, planning_limits, solve_where_it_stands
    from cell.trajectory.sources import Points

    out = []
    for p in found:
        if isinstance(p, Poses):
            limits = planning_limits(config, p.robot, speed)
            traj = await solve_where_it_stands(bus, config, p.robot, p, limits)
            joints = list(arm_model(config.robot(p.robot).model).joints)
            p = Points(joints, traj.t, traj.q, None, None, p.robot, p.name, p.source)
        out.append(p)
    return out


def messages(found: list) -> list:
    """The joint points as the bus carries them (controller.follow and controller.name alike)."""
    from cell.trajectory.wire import to_message

    return [to_message(p.robot, p.t, p.q, p.qd, p.qdd, p.joint_names, p.name) for p in found]


async def _name(config, found, name: str, speed: float = 0.5) -> int:
    from cell.bus import Bus, BusError, RemoteError
    from cell.trajectory.model import TrajectoryError
    from cell.v1 import controller_pb2

    try:
        async with Bus.connect(config.bus, "cell-follow") as bus:
            found = await joint_points(bus, config, found, speed)
            req = controller_pb2.NameRequest(name=name, trajectories=messages(found))
            reply = await bus.request("controller", "name", req, controller_pb2.NameReply, timeout=60.0)
    except (RemoteError, TrajectoryError) as exc:
        print(f"cell follow: {getattr(exc, 'message', exc)}", file=sys.stderr)
        return 2
    except BusError as exc:
        print(f"cell follow: no cell answered ({exc})", file=sys.stderr)
        return 1
    robots = ", ".join(reply.robots)
    print(
        f"named {reply.name!r}: {robots}, {reply.points} points over {reply.duration_s:.2f} s; "
        f"run it with {reply.name!r} as follow:{reply.name} on a skill server"
    )
    return 0


async def _follow(config, found, speed: float, replace: bool) -> int:
    import contextlib

    import numpy as np

    from cell.bus import Bus, BusError, FaultCode, RemoteError
    from cell.robot.arm import arm_model
    from cell.robot.truth import Truth
    from cell.trajectory.model import Trajectory, TrajectoryError
    from cell.v1 import controller_pb2

    try:
        async with Bus.connect(config.bus, "cell-follow") as bus:
            found = await joint_points(bus, config, found, speed / 100.0)
            req = controller_pb2.FollowRequest(speed=speed, trajectories=messages(found), replace=replace)
            longest = max(float(p.t[-1] - p.t[0]) for p in found)
            async with Truth.watching(bus) as truth:
                reply = await bus.request(
                    "controller", "follow", req, controller_pb2.MoveReply, timeout=longest + 120.0
                )
                for p in found:
                    await truth.until(p.robot, reply.t_end_ns + 20_000_000)
    except TrajectoryError as exc:
        print(f"cell follow: {exc}", file=sys.stderr)
        return 2
    except RemoteError as exc:
        print(f"cell follow: {exc.message}", file=sys.stderr)
        return 2 if exc.code in (FaultCode.BAD_REQUEST, FaultCode.PLAN, FaultCode.UNKNOWN_ROBOT) else 1
    except BusError as exc:
        print(f"cell follow: no cell answered ({exc})", file=sys.stderr)
        return 1
    starts = []  # each robot's start against its plan's: when it got 1 mrad off, less when the plan did
    for p in found:
        arm = arm_model(config.robot(p.robot).model)
        traj = Trajectory.build(p.t, p.q, joint_names=p.joint_names or None, robot_joints=arm.joints)
        q_real = truth.at(p.robot, reply.t0_ns + traj.t * 1e9)
        err = np.array(
            [np.linalg.norm(arm.fk(a)[0] - arm.fk(b)[0]) for a, b in zip(q_real, traj.q, strict=True)]
        )
        err *= 1000
        print(
            f"{p.robot}: {traj.points} points over {traj.duration:.2f} s ({p.name or p.source}); tool path "
            f"error at the points max {err.max():.3f} mm (t = {traj.t[int(err.argmax())]:.3f} s), "
            f"median {np.median(err):.3f} mm"
        )
        with contextlib.suppress(IndexError):  # (a robot that never moved has no start)
            moved = truth.start_of_motion(p.robot, reply.t0_ns - 20_000_000)
            starts.append(moved - reply.t0_ns - traj.starts_moving_s() * 1e9)
    if reply.tps_per_s:
        print(
            f"TPs fitted to the plan: {reply.tps_per_s:.1f} a second, the modelled tool within "
            f"{reply.fitted_deviation_mm:.4f} mm of it"
        )
    if len(starts) > 1:
        print(f"start shift between robots: {(max(starts) - min(starts)) / 1e6:.2f} ms")
    return 0


register(
    Command(
        "follow",
        "run a trajectory planned elsewhere (JSON, CSV, ROS 2 bag) on a running cell",
        arguments,
        run,
        rank=4,
    )
)
