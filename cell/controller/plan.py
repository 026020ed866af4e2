"""Motions: joint-space with ruckig (jerk-limited, time-optimal, all joints synchronised), linear
tool motions (Cartesian interpolation timed by a 1-D ruckig profile, then IK with continuity
checks), and stops (ruckig's velocity interface: to standstill within the limits).

ruckig rather than hand-rolled profiles: it plans from any start state (a moving robot, for
re-planning and stops) to any target state in microseconds, with velocity, acceleration and
jerk limits per joint, and is the trajectory generator robot makers and MoveIt use.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Trajectory

from cell.robot.kinematics import Kinematics, Unreachable
from cell.robot.pose import rotation_error, slerp
from cell.trajectory.motion import Motion


class PlanError(ValueError):
    """A motion that cannot be planned within the limits (its reason says why)."""


@dataclass(frozen=True)
class MotionLimits:
    """Per-joint limits a motion must keep (SI), and the tool's for linear motions."""

    v_max: np.ndarray  # rad/s
    a_max: np.ndarray  # rad/s^2
    j_max: np.ndarray  # rad/s^3
    tool_v_max: float = 0.25  # m/s
    tool_a_max: float = 1.0  # m/s^2
    tool_j_max: float = 10.0  # m/s^3
    tool_w_max: float = 1.0  # rad/s, turning the tool

    def scaled(self, speed: float) -> MotionLimits:
        """A speed factor in (0, 1]: velocities x s, accelerations x s^2, jerks x s^3, so that a
        time-optimal motion keeps its path and takes 1/s as long."""
        if not 0.0 < speed <= 1.0:
            raise PlanError(f"speed must be in (0, 100] %, got {speed * 100:g} %")
        s = speed
        return replace(
            self,
            v_max=self.v_max * s,
            a_max=self.a_max * s**2,
            j_max=self.j_max * s**3,
            tool_v_max=self.tool_v_max * s,
            tool_a_max=self.tool_a_max * s**2,
            tool_j_max=self.tool_j_max * s**3,
            tool_w_max=self.tool_w_max * s,
        )


class RuckigMotion(Motion):
    def __init__(self, traj: Trajectory, dof: int) -> None:
        self.traj, self.dof, self.duration = traj, dof, float(traj.duration)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.empty((len(t), self.dof))
        v = np.empty((len(t), self.dof))
        for i, ti in enumerate(np.clip(t, 0.0, self.duration).tolist()):
            p, vel, _ = self.traj.at_time(ti)
            q[i], v[i] = p, vel
        return q, v


def _ruckig(inp: InputParameter, dof: int, what: str) -> RuckigMotion:
    traj = Trajectory(dof)
    try:
        result = Ruckig(dof).calculate(inp, traj)
    except RuckigError:
        # ruckig 0.19 fails on a few exact limit combinations (v 12.2214030136737, a 47.796061319242,
        # j 467.307942278978 for a 0-to-1 profile): the same with the jerk limit 0.01 % lower plans
        inp.max_jerk = [j * 0.9999 for j in inp.max_jerk]
        try:
            result = Ruckig(dof).calculate(inp, traj)
        except RuckigError as exc:
            first = str(exc).strip().splitlines()[0]
            raise PlanError(f"{what}: ruckig could not plan it ({first})") from None
    if result not in (Result.Working, Result.Finished):
        raise PlanError(f"{what}: ruckig could not plan it ({result.name})")
    return RuckigMotion(traj, dof)


def _input(dof: int, limits: MotionLimits, q0: np.ndarray, v0: np.ndarray | None) -> InputParameter:
    inp = InputParameter(dof)
    inp.current_position = np.asarray(q0, np.float64).tolist()
    inp.current_velocity = (np.zeros(dof) if v0 is None else np.asarray(v0, np.float64)).tolist()
    inp.current_acceleration = [0.0] * dof
    inp.max_velocity = np.resize(limits.v_max, dof).tolist()
    inp.max_acceleration = np.resize(limits.a_max, dof).tolist()
    inp.max_jerk = np.resize(limits.j_max, dof).tolist()
    return inp


def plan_joint(q0: np.ndarray, q1: np.ndarray, limits: MotionLimits, v0: np.ndarray | None = None) -> Motion:
    """To joint positions q1 at rest, from q0 (moving at v0, or at rest); all joints arrive together."""
    q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
    inp = _input(q0.size, limits, q0, v0)
    inp.target_position = q1.tolist()
    inp.target_velocity = [0.0] * q0.size
    return _ruckig(inp, q0.size, "joint motion")


def plan_stop(q0: np.ndarray, v0: np.ndarray, limits: MotionLimits) -> Motion:
    """From q0 moving at v0 to standstill as soon as the limits allow."""
    q0 = np.asarray(q0, np.float64)
    inp = _input(q0.size, limits, q0, v0)
    inp.control_interface = ControlInterface.Velocity
    inp.target_velocity = [0.0] * q0.size
    inp.target_acceleration = [0.0] * q0.size
    return _ruckig(inp, q0.size, "stop")


class SampledMotion(Motion):
    """Joint positions known at fixed times (a linear motion after IK); linear in between."""

    def __init__(self, t: np.ndarray, q: np.ndarray) -> None:
        self.t, self.q = t, q
        self.duration, self.dof = float(t[-1]), q.shape[1]
        dt = np.diff(t)[:, None]
        v = np.diff(q, axis=0) / dt
        self.v = np.vstack([np.zeros((1, self.dof)), (v[1:] + v[:-1]) / 2, np.zeros((1, self.dof))])

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.clip(np.asarray(t, np.float64), 0.0, self.duration)
        q = np.stack([np.interp(t, self.t, self.q[:, j]) for j in range(self.dof)], axis=1)
        v = np.stack([np.interp(t, self.t, self.v[:, j]) for j in range(self.dof)], axis=1)
        return q, v


class ChainedMotion(Motion):
    """Motions one after another, each starting at rest where the last ended, then held `pad` s."""

    def __init__(self, parts: list[Motion], pad: float = 0.0) -> None:
        self.parts = parts
        self.starts = np.concatenate([[0.0], np.cumsum([p.duration for p in parts])])
        self.duration, self.dof = float(self.starts[-1] + pad), parts[0].dof
        if any(p.knots is not None for p in parts):  # (each part's, and where each begins)
            own = [p.knots + s for p, s in zip(parts, self.starts, strict=False) if p.knots is not None]
            self.knots = np.unique(np.concatenate([self.starts[1:-1], *own]))

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.clip(np.asarray(t, np.float64), 0.0, self.duration)
        q, v = np.empty((t.size, self.dof)), np.empty((t.size, self.dof))
        which = np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.parts) - 1)
        for i, part in enumerate(self.parts):
            mask = which == i
            if mask.any():
                q[mask], v[mask] = part.sample(t[mask] - self.starts[i])
        return q, v


def plan_loop(
    q0: np.ndarray, waypoints: list[np.ndarray], limits: MotionLimits, lap_quantum_s: float
) -> Motion:
    """From q0 through each waypoint (at rest at each) and back to q0, one lap; held at q0 at the end
    so that a lap lasts a whole number of lap_quantum_s (a command window: every lap then meets the
    robot's windows as the first did, and the TPs fitted for it fit them all)."""
    stops = [np.asarray(q0, np.float64), *(np.asarray(w, np.float64) for w in waypoints), q0]
    parts = [plan_joint(a, b, limits) for a, b in itertools.pairwise(stops)]
    total = sum(p.duration for p in parts)
    pad = math.ceil(total / lap_quantum_s - 1e-9) * lap_quantum_s - total
    return ChainedMotion(parts, pad)


def plan_linear(
    kin: Kinematics,
    q0: np.ndarray,
    pos1: np.ndarray,
    rot1: np.ndarray,
    limits: MotionLimits,
    step_s: float = 0.004,
) -> Motion:
    """The tool along a straight line (and turning about one axis) from where q0 puts it to
    (pos1, rot1), at rest at both ends; PlanError if IK fails on the way, a joint would jump
    (a singularity or a branch change) or go faster than its limit.

    The line is timed by the tool's limits first; where that asks a joint for more velocity or
    acceleration than its own limits allow (near the base or a wrist singularity a few
    cm/s of tool speed can take rad/s), the whole line is slowed down by the factor that
    brings the worst joint within them: the path stays, the joints keep their limits, and
    the data plane is never handed a reference its drives cannot follow."""
    q0 = np.asarray(q0, np.float64)
    pos0, rot0 = kin.fk(q0)
    length = float(np.linalg.norm(pos1 - pos0))
    angle = float(np.linalg.norm(rotation_error(rot1, rot0)))
    if length < 1e-9 and angle < 1e-9:
        return SampledMotion(np.array([0.0, 1e-3]), np.vstack([q0, q0]))
    t, q = _line(kin, q0, (pos0, pos1), (rot0, rot1), (length, angle), limits, step_s, check=False)
    dt = t[1] - t[0]
    v = np.abs(np.gradient(q, dt, axis=0)).max(axis=0)
    a = np.abs(np.gradient(np.gradient(q, dt, axis=0), dt, axis=0)).max(axis=0)
    f = min(
        1.0,
        float((limits.v_max / np.maximum(v, 1e-12)).min()),
        float(np.sqrt(limits.a_max / np.maximum(a, 1e-12)).min()),
    )
    if f < 1.0:
        f = max(f * 0.98, _SLOWEST)
        slow = replace(
            limits,
            tool_v_max=limits.tool_v_max * f,
            tool_a_max=limits.tool_a_max * f**2,
            tool_j_max=limits.tool_j_max * f**3,
            tool_w_max=limits.tool_w_max * f,
        )
        t, q = _line(kin, q0, (pos0, pos1), (rot0, rot1), (length, angle), slow, step_s, check=True)
    else:
        _check_jumps(t, q, limits)
    return SampledMotion(t, q)


_SLOWEST = 0.05  # a line slowed further than this is a singularity or a branch change: refused


def _line(
    kin: Kinematics,
    q0: np.ndarray,
    pos: tuple[np.ndarray, np.ndarray],
    rot: tuple[np.ndarray, np.ndarray],
    extent: tuple[float, float],
    limits: MotionLimits,
    step_s: float,
    check: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """The line timed by one path parameter u in [0, 1] (the tool's speed along it and its turning
    limit it), sampled every step_s and solved by IK from sample to sample."""
    (pos0, pos1), (rot0, rot1), (length, angle) = pos, rot, extent
    scale = max(length / limits.tool_v_max, angle / limits.tool_w_max)  # s of travel at full speed
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [1.0]
    inp.max_velocity = [1.0 / scale]
    inp.max_acceleration = [min(limits.tool_a_max / max(length, 1e-9), limits.tool_a_max / max(angle, 1e-9))]
    inp.max_jerk = [min(limits.tool_j_max / max(length, 1e-9), limits.tool_j_max / max(angle, 1e-9))]
    timing = _ruckig(inp, 1, "linear motion")
    n = max(2, math.ceil(timing.duration / step_s) + 1)
    t = np.linspace(0.0, timing.duration, n)
    u = timing.sample(t)[0][:, 0]
    q = np.empty((n, q0.size))
    q[0] = q0
    for i in range(1, n):
        p = pos0 + (pos1 - pos0) * u[i]
        r = slerp(rot0, rot1, float(u[i]))
        try:
            q[i] = kin.ik(p, r, q[i - 1])
        except Unreachable as exc:
            raise PlanError(f"linear motion: {100 * u[i]:.0f}% of the way: {exc.reason}") from None
    if check:
        _check_jumps(t, q, limits, u)
    return t, q


def _check_jumps(t: np.ndarray, q: np.ndarray, limits: MotionLimits, u: np.ndarray | None = None) -> None:
    """PlanError where a joint would go faster than its limit between two samples."""
    jump = np.abs(np.diff(q, axis=0)) / (t[1] - t[0])
    over = np.argwhere(jump > limits.v_max * 1.05)
    if over.size:
        i, j = (int(x) for x in over[0])
        where = "" if u is None else f" {100 * u[i + 1]:.0f}% of the way"
        raise PlanError(
            f"linear motion: joint {j + 1} would need {jump[i, j]:.2f} rad/s{where} "
            f"(limit {limits.v_max[j]:.2f}): a singularity or a branch change; use a joint move"
        )
