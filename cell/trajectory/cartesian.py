"""Cartesian paths: tool poses (with times, or a maximum tool speed) as a joint trajectory through the
robot model's IK (cell.robot.kinematics), so that they run as any trajectory does.

With times, each pose is a point of the trajectory, solved from the one before (the first from
where the robot stands: the branch nearest its joints).  With a maximum tool speed instead, the
tool goes straight from pose to pose, at rest at each (a 1 - cos speed profile whose peak is the
maximum), turning by slerp, sampled at `rate_hz`: the path between waypoints is the line, not what
a joint spline would make of it.  A pose out of reach, or a step that would flip the arm onto
another IK branch, is a TrajectoryError naming the waypoint.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics, Unreachable
from cell.robot.pose import rotation_error, slerp
from cell.trajectory.model import MAX_POINTS, Trajectory, TrajectoryError
from cell.v1 import controller_pb2

BRANCH_JUMP_RAD = 0.5  # a joint moving more than this between two samples changed IK branch


@dataclass
class Poses:
    """Tool poses of one robot, as a source gives them (positions in m in its base frame)."""

    positions: np.ndarray  # (n, 3)
    rotations: np.ndarray | None = None  # (n, 3, 3); None: the tool keeps its orientation
    t: np.ndarray | None = None  # s at each pose; None: max_speed times them
    max_speed: float | None = None  # m/s of the tool
    robot: str = ""
    name: str = ""
    source: str = ""


def quaternion_matrix(xyzw: Sequence[float]) -> np.ndarray:
    """A rotation matrix from a unit quaternion in geometry_msgs' order (x, y, z, w)."""
    x, y, z, w = (float(v) for v in xyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-9:
        raise TrajectoryError(f"orientation {list(xyzw)} is not a quaternion")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def solve(
    kin: Kinematics,
    q_start: Sequence[float] | np.ndarray,
    poses: Poses,
    rate_hz: float = 50.0,
    turn_speed: float = 1.0,
) -> Trajectory:
    """The joint trajectory of the poses (see the module's docstring); turn_speed (rad/s) bounds the
    tool's turning as max_speed bounds its travel."""
    p = np.asarray(poses.positions, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 1:
        raise TrajectoryError(f"positions: {p.shape} (one row of x, y, z a pose)")
    if not np.isfinite(p).all():
        raise TrajectoryError(f"pose {int(np.argwhere(~np.isfinite(p))[0][0])}: position not a finite number")
    q_start = np.asarray(q_start, np.float64)
    here = kin.fk(q_start)[1]
    rots = (
        np.repeat(here[None], len(p), 0)
        if poses.rotations is None
        else np.asarray(poses.rotations, np.float64)
    )
    if rots.shape != (len(p), 3, 3):
        raise TrajectoryError(f"rotations: {rots.shape} for {len(p)} poses")
    if poses.t is not None:
        t = np.asarray(poses.t, np.float64)
        if t.shape != (len(p),):
            raise TrajectoryError(f"{t.size} times for {len(p)} poses")
        samples = [(_waypoint(k, p), p[k], rots[k]) for k in range(len(p))]
    else:
        if poses.max_speed is None or not poses.max_speed > 0:
            raise TrajectoryError("Cartesian poses need times or a maximum tool speed (m/s) > 0")
        if len(p) < 2:
            raise TrajectoryError("a Cartesian path needs at least 2 poses")
        t_list, samples = [0.0], [(_waypoint(0, p), p[0], rots[0])]
        for k in range(len(p) - 1):
            length = float(np.linalg.norm(p[k + 1] - p[k]))
            angle = float(np.linalg.norm(rotation_error(rots[k + 1], rots[k])))
            span = math.pi / 2 * max(length / poses.max_speed, angle / turn_speed)  # peak speed = the limit
            if span <= 0:
                continue
            n = max(2, math.ceil(span * rate_hz) + 1)
            start = t_list[-1]
            for i, ts in enumerate(np.linspace(0.0, span, n)[1:], 1):
                s = (1 - math.cos(math.pi * ts / span)) / 2
                pos, rot = p[k] + (p[k + 1] - p[k]) * s, slerp(rots[k], rots[k + 1], s)
                on = f"{100 * s:.0f}% of the way from waypoint {k} to {k + 1}"
                samples.append((_waypoint(k + 1, p) if i == n - 1 else on, pos, rot))
                t_list.append(start + float(ts))
        t = np.array(t_list)
    if len(samples) > MAX_POINTS:
        raise TrajectoryError(f"{len(samples):,} points: at most {MAX_POINTS:,} (a lower rate_hz?)")
    if poses.t is None:  # every waypoint within reach, before the path between them is solved
        near = q_start
        for k in range(len(p)):
            try:
                near = kin.ik(p[k], rots[k], near)
            except Unreachable as exc:
                raise TrajectoryError(f"{_waypoint(k, p)}: {exc.reason}") from None
    q = np.empty((len(samples), q_start.size))
    near = q_start
    for i, (where, pos, rot) in enumerate(samples):
        try:
            q[i] = kin.ik(pos, rot, near)
        except Unreachable as exc:
            raise TrajectoryError(f"{where}: {exc.reason}") from None
        if i and np.abs(q[i] - near).max() > BRANCH_JUMP_RAD:
            j = int(np.abs(q[i] - near).argmax())
            raise TrajectoryError(
                f"{where}: joint {j + 1} would jump {abs(q[i, j] - near[j]):.2f} rad on the way there "
                "(a singularity or another IK branch): add poses between, or move there by joints"
            )
        near = q[i]
    return Trajectory.build(t, q, name=poses.name)


def _waypoint(k: int, p: np.ndarray) -> str:
    return f"waypoint {k} ({', '.join(f'{v * 1000:.1f}' for v in p[k])} mm)"


async def solve_where_it_stands(bus, config, robot: str, poses: Poses) -> Trajectory:
    """solve() from the robot's joints as the controller reports them now, with its model's IK (for a
    task script's Cell.cartesian and `cell follow` alike)."""
    req = controller_pb2.RobotRequest(robot=robot)
    here = await bus.request("controller", "pose", req, controller_pb2.PoseReply, timeout=10.0)
    return solve(Kinematics(arm_model(config.robot(robot).model)), list(here.joints), poses)
