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
from ruckig import InputParameter, Result, Ruckig
from ruckig import Trajectory as RuckigTrajectory

from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics, Unreachable
from cell.robot.pose import rotation_error, slerp
from cell.trajectory.model import MAX_POINTS, Trajectory, TrajectoryError
from cell.v1 import controller_pb2

BRANCH_JUMP_RAD = 0.5  # a joint moving more than this between two samples changed IK branch
PATH_GRID = 64  # samples of a straight leg's joint path, for the limits of its ruckig timing


@dataclass(frozen=True)
class JointLimits:
    """What an untimed path's joints may do (rad/s, rad/s^2, rad/s^3 per joint; the tool's m/s)."""

    v_max: np.ndarray
    a_max: np.ndarray
    j_max: np.ndarray
    tool_v_max: float = math.inf


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
    limits: JointLimits | None = None,
) -> Trajectory:
    """The joint trajectory of the poses (see the module's docstring); turn_speed (rad/s) bounds the
    tool's turning as max_speed bounds its travel.  Poses with neither times nor a maximum speed are
    timed by ruckig within `limits` (_ruckig_path): each straight leg as fast as its joints allow."""
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
    elif poses.max_speed is None and limits is not None:
        if len(p) < 2:
            raise TrajectoryError("a Cartesian path needs at least 2 poses")
        return _ruckig_path(kin, q_start, p, rots, limits, rate_hz, poses.name)
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
                on, pos, rot = _on_leg(p, rots, k, (1 - math.cos(math.pi * ts / span)) / 2)
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
    return Trajectory.build(t, _solve_along(kin, q_start, samples, jump_from_start=False), name=poses.name)


def _on_leg(p: np.ndarray, rots: np.ndarray, k: int, s: float) -> tuple[str, np.ndarray, np.ndarray]:
    """Where the tool is at path parameter s of leg k (waypoint k to k + 1): (in words, position,
    rotation), the line and a slerp."""
    where = f"{100 * s:.0f}% of the way from waypoint {k} to {k + 1}"
    return where, p[k] + (p[k + 1] - p[k]) * s, slerp(rots[k], rots[k + 1], s)


def _solve_along(
    kin: Kinematics,
    near: np.ndarray,
    samples: list[tuple[str, np.ndarray, np.ndarray]],
    jump_from_start: bool,
) -> np.ndarray:
    """The joints at each (where, position, rotation), each solved from the one before (the first
    from `near`); TrajectoryError naming where a pose is out of reach or a joint would jump (another
    IK branch): from `near` too if jump_from_start."""
    q = np.empty((len(samples), near.size))
    for i, (where, pos, rot) in enumerate(samples):
        try:
            q[i] = kin.ik(pos, rot, near)
        except Unreachable as exc:
            raise TrajectoryError(f"{where}: {exc.reason}") from None
        if (i or jump_from_start) and np.abs(q[i] - near).max() > BRANCH_JUMP_RAD:
            j = int(np.abs(q[i] - near).argmax())
            raise TrajectoryError(
                f"{where}: joint {j + 1} would jump {abs(q[i, j] - near[j]):.2f} rad on the way there "
                "(a singularity or another IK branch): add poses between, or move there by joints"
            )
        near = q[i]
    return q


def _leg_ik(
    kin: Kinematics, near: np.ndarray, p: np.ndarray, rots: np.ndarray, k: int, s: np.ndarray
) -> np.ndarray:
    """The joints along leg k at path parameters s, from `near` (_solve_along)."""
    return _solve_along(kin, near, [_on_leg(p, rots, k, float(x)) for x in s], jump_from_start=True)


def _ruckig_path(
    kin: Kinematics,
    q_start: np.ndarray,
    p: np.ndarray,
    rots: np.ndarray,
    limits: JointLimits,
    rate_hz: float,
    name: str,
) -> Trajectory:
    """Each straight leg, at rest at both ends, timed by a 1-D ruckig profile of its path parameter s
    in [0, 1] whose limits keep every joint within its own: with the joint path q(s) (IK on a grid),
    q' s_dot <= v, q'' s_dot^2 + q' s_ddot <= a and q' s_dddot <= j (with a margin for the cross
    terms jerk has), the tool within tool_v_max."""
    t_all, q_all, t0 = [0.0], [kin.ik(p[0], rots[0], q_start)], 0.0
    grid = np.linspace(0.0, 1.0, PATH_GRID)
    for k in range(len(p) - 1):
        q = _leg_ik(kin, q_all[-1], p, rots, k, grid)
        d1 = np.abs(np.gradient(q, grid, axis=0)).max(axis=0)
        d2 = np.abs(np.gradient(np.gradient(q, grid, axis=0), grid, axis=0)).max(axis=0)
        length = float(np.linalg.norm(p[k + 1] - p[k]))
        if d1.max() < 1e-9:
            continue  # (the same pose again)
        sv = min(float(np.min(limits.v_max / np.maximum(d1, 1e-9))), limits.tool_v_max / max(length, 1e-9))
        sv = min(sv, float(np.min(np.sqrt(0.5 * limits.a_max / np.maximum(d2, 1e-9)))))
        sa = float(np.min((limits.a_max - d2 * sv * sv) / np.maximum(d1, 1e-9)))
        sj = 0.5 * float(np.min(limits.j_max / np.maximum(d1, 1e-9)))
        inp = InputParameter(1)
        inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
        inp.target_position, inp.target_velocity, inp.target_acceleration = [1.0], [0.0], [0.0]
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = [sv], [sa], [sj]
        traj = RuckigTrajectory(1)
        if Ruckig(1).calculate(inp, traj) not in (Result.Working, Result.Finished):
            raise TrajectoryError(f"{_waypoint(k + 1, p)}: no timing within the joints' limits")
        n = max(2, math.ceil(traj.duration * rate_hz) + 1)
        ts = np.linspace(0.0, traj.duration, n)[1:]
        s = np.clip([traj.at_time(float(x))[0][0] for x in ts], 0.0, 1.0)
        q_all += list(_leg_ik(kin, q_all[-1], p, rots, k, np.asarray(s)))
        t_all += (t0 + ts).tolist()
        t0 += float(traj.duration)
    if len(t_all) > MAX_POINTS:
        raise TrajectoryError(f"{len(t_all):,} points: at most {MAX_POINTS:,} (a lower rate_hz?)")
    return Trajectory.build(np.array(t_all), np.array(q_all), name=name)


def _waypoint(k: int, p: np.ndarray) -> str:
    return f"waypoint {k} ({', '.join(f'{v * 1000:.1f}' for v in p[k])} mm)"


def planning_limits(config, robot: str, speed: float = 0.5) -> JointLimits:
    """The limits the controller plans the robot's own motions with (its model's, under the data
    plane's v_max and [controller] a_max, j_max, tool_v_max), scaled by `speed` as its motions are
    (v s, a s^2, j s^3): what an untimed Cartesian path is timed within."""
    lim = arm_model(config.robot(robot).model).limits
    cc, n = config.controller, lim.v_max.size
    v = np.minimum(lim.v_max, np.resize(np.array(config.dataplane.v_max), n))
    a = np.minimum(lim.a_max, np.resize(np.array(cc.a_max), n))
    j = np.resize(np.array(cc.j_max, np.float64), n)
    return JointLimits(v * speed, a * speed**2, j * speed**3, cc.tool_v_max * speed)


async def solve_where_it_stands(
    bus, config, robot: str, poses: Poses, limits: JointLimits | None = None
) -> Trajectory:
    """solve() from the robot's joints as the controller reports them now, with its model's IK (for a
    task script's Cell.cartesian and `cell follow` alike)."""
    req = controller_pb2.RobotRequest(robot=robot)
    here = await bus.request("controller", "pose", req, controller_pb2.PoseReply, timeout=10.0)
    return solve(Kinematics(arm_model(config.robot(robot).model)), list(here.joints), poses, limits=limits)
