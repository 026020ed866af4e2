"""Joint trajectories planned elsewhere (MoveIt, a recorded demonstration, any planner): the points, as
a `Trajectory`, checked against a robot model before anything moves, and the `TimedMotion` the
controller cuts into TPs and streams like its own motions (seed 000, Sec. 6: the Trajectory Exporter
hands time-stamped points to the industrial controller).

Between points the motion is a cubic Hermite spline through each point's position and velocity; a
trajectory without velocities gets them from the cubic spline through its positions (continuous
acceleration, at rest at both ends, as a planner's trajectories are), one tridiagonal solve per
joint.  Accelerations given with the points are checked, not used.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cell.trajectory.motion import Motion

MAX_POINTS = 1_000_000
LIMIT_SLACK = 1.05  # a planner's points may graze a limit by rounding: 5 % over is refused


class TrajectoryError(ValueError):
    """A trajectory the cell will not run; the message names the first offending point."""


@dataclass(frozen=True)
class Trajectory:
    """Points of one robot: times from the start (s, increasing, the first 0), positions (rad, one row
    a point, one column a joint in the robot's order), and velocities / accelerations if the planner
    gave them (else None)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray | None = None
    qdd: np.ndarray | None = None
    name: str = ""

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    @property
    def points(self) -> int:
        return int(self.t.size)

    def starts_moving_s(self, dist: float = 1e-3) -> float:
        """When its plan first gets `dist` rad from its first point, to 0.1 ms (as
        cell.robot.truth.Truth.start_of_motion reads a robot: two robots whose plans start unlike
        are each held to their own)."""
        t = np.arange(0.0, self.duration, 1e-4)
        q = TimedMotion(self).sample(t)[0]
        off = np.flatnonzero(np.abs(q - q[0]).max(axis=1) >= dist)
        return float(t[off[0]]) if off.size else 0.0

    @staticmethod
    def build(
        t: Sequence[float] | np.ndarray,
        q: Sequence[Sequence[float]] | np.ndarray,
        qd: Sequence[Sequence[float]] | np.ndarray | None = None,
        qdd: Sequence[Sequence[float]] | np.ndarray | None = None,
        joint_names: Sequence[str] | None = None,
        robot_joints: Sequence[str] | None = None,
        name: str = "",
    ) -> Trajectory:
        """From arrays (numpy or lists), the points' columns put in the robot's joint order if named;
        TrajectoryError for a shape, a value or a time that cannot be a trajectory."""
        t_arr = np.asarray(t, np.float64)
        if t_arr.ndim != 1 or t_arr.size < 2:
            raise TrajectoryError(f"a trajectory needs at least 2 points (got {t_arr.size})")
        if t_arr.size > MAX_POINTS:
            raise TrajectoryError(f"{t_arr.size} points: at most {MAX_POINTS:,}")
        cols = None
        if joint_names is not None and robot_joints is not None:
            cols = joint_order(joint_names, robot_joints)
        arrays: list[np.ndarray | None] = []
        for what, a in (("positions", q), ("velocities", qd), ("accelerations", qdd)):
            if a is None:
                arrays.append(None)
                continue
            arr = np.asarray(a, np.float64)
            if arr.ndim != 2 or arr.shape[0] != t_arr.size:
                raise TrajectoryError(f"{what}: {arr.shape} for {t_arr.size} points (one row a point)")
            if cols is not None:
                if arr.shape[1] != len(cols):
                    raise TrajectoryError(f"{what}: {arr.shape[1]} columns for {len(cols)} joint names")
                arr = arr[:, np.argsort(cols)]
            bad = np.argwhere(~np.isfinite(arr))
            if bad.size:
                raise TrajectoryError(f"point {int(bad[0][0])}: {what} not a finite number (NaN or inf)")
            arrays.append(arr)
        bad_t = np.flatnonzero(~np.isfinite(t_arr))
        if bad_t.size:
            raise TrajectoryError(f"point {int(bad_t[0])}: its time is not a finite number")
        t_arr = t_arr - t_arr[0]
        back = np.flatnonzero(np.diff(t_arr) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise TrajectoryError(
                f"point {i}: time {t_arr[i]:.6g} s does not come after point {i - 1}'s ({t_arr[i - 1]:.6g} s)"
            )
        q_arr, qd_arr, qdd_arr = arrays
        assert q_arr is not None  # (q is not optional)
        return Trajectory(t_arr, q_arr, qd_arr, qdd_arr, name)

    def check(self, q_min: np.ndarray, q_max: np.ndarray, v_max: np.ndarray, a_max: np.ndarray) -> None:
        """TrajectoryError naming the first point that leaves the robot's limits (TimedMotion.check)."""
        TimedMotion(self).check(q_min, q_max, v_max, a_max)


def joint_order(names: Sequence[str], robot_joints: Sequence[str]) -> list[int]:
    """The robot's joint index of each name: UR's ROS names (`shoulder_pan_joint`, with or without a
    prefix such as `ur5e_` or `r1_`), the cell's own (`shoulder_pan`), or j1..jN; every joint once."""
    out = []
    for n in names:
        key = n.strip()
        found = None
        for k, joint in enumerate(robot_joints):
            ros = f"{joint}_joint"
            if key in (joint, ros, f"j{k + 1}") or key.endswith((f"_{ros}", f"/{ros}")):
                found = k
                break
        if found is None:
            known = ", ".join(f"{j}_joint" for j in robot_joints)
            raise TrajectoryError(f"joint name {n!r} is not one of this robot's ({known})")
        out.append(found)
    if sorted(out) != list(range(len(robot_joints))):
        n_joints = len(robot_joints)
        raise TrajectoryError(
            f"joint names {list(names)} do not name each of the robot's {n_joints} joints once"
        )
    return out


def spline_velocities(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The velocities of the clamped cubic spline through (t, q), at rest at both ends: continuous
    acceleration through every point.  The tridiagonal system of the knots' slopes, solved once for
    all joints (Thomas algorithm)."""
    n = t.size
    v = np.zeros_like(q)
    if n <= 2:
        return v
    h = np.diff(t)
    d = np.diff(q, axis=0) / h[:, None]  # secant slopes
    # interior knots i = 1..n-2:
    #   h[i] v[i-1] + 2 (h[i-1] + h[i]) v[i] + h[i-1] v[i+1] = 3 (h[i] d[i-1] + h[i-1] d[i])
    lower, diag, upper = h[1:], 2 * (h[:-1] + h[1:]), h[:-1]
    rhs = 3 * (h[1:, None] * d[:-1] + h[:-1, None] * d[1:])
    m = n - 2
    c = np.empty(m)
    r = np.empty_like(rhs)
    c[0] = upper[0] / diag[0]
    r[0] = rhs[0] / diag[0]
    for i in range(1, m):  # (v[0] = v[n-1] = 0: the ends' terms vanish)
        den = diag[i] - lower[i] * c[i - 1]
        c[i] = upper[i] / den if i < m - 1 else 0.0
        r[i] = (rhs[i] - lower[i] * r[i - 1]) / den
    for i in range(m - 2, -1, -1):
        r[i] -= c[i] * r[i + 1]
    v[1:-1] = r
    return v


class TimedMotion(Motion):
    """A trajectory as a motion: the cubic Hermite spline through its points' positions and velocities
    (the spline's own velocities where the planner gave none)."""

    def __init__(self, traj: Trajectory) -> None:
        self.traj = traj
        self.t, self.q = traj.t, traj.q
        self.qd = traj.qd if traj.qd is not None else spline_velocities(traj.t, traj.q)
        self.duration, self.dof = traj.duration, traj.q.shape[1]
        self.knots = traj.t  # (TP sections end on the points: the robot is on the plan there)

    def _segment(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.clip(np.asarray(t, np.float64), 0.0, self.duration)
        k = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 2)
        h = (self.t[k + 1] - self.t[k])[:, None]
        s = ((t - self.t[k])[:, None]) / h
        return k, h, s

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k, h, s = self._segment(t)
        p0, p1, m0, m1 = self.q[k], self.q[k + 1], self.qd[k] * h, self.qd[k + 1] * h
        s2, s3 = s * s, s * s * s
        q = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * m1
        v = (6 * s2 - 6 * s) * (p0 - p1) + (3 * s2 - 4 * s + 1) * m0 + (3 * s2 - 2 * s) * m1
        v = v / h
        return q, v

    def check(self, q_min: np.ndarray, q_max: np.ndarray, v_max: np.ndarray, a_max: np.ndarray) -> None:
        """TrajectoryError naming the first point that leaves the robot's limits (its position range,
        its velocity and acceleration, given or as the spline through the points has them)."""
        traj, dof = self.traj, q_min.size
        if self.q.shape[1] != dof:
            raise TrajectoryError(f"{self.q.shape[1]} joints per point for a robot of {dof}")
        checks = [
            ("position", self.q, None, q_min, q_max),
            ("velocity", self.qd, None, -v_max * LIMIT_SLACK, v_max * LIMIT_SLACK),
            ("acceleration", self.acceleration(), traj.qdd, -a_max * LIMIT_SLACK, a_max * LIMIT_SLACK),
        ]
        first: tuple[int, str] | None = None
        for what, values, given, lo, hi in checks:
            for arr in (values, given):
                if arr is None:
                    continue
                out = np.argwhere((arr < lo) | (arr > hi))
                if out.size and (first is None or out[0][0] < first[0]):
                    i, j = (int(x) for x in out[0])
                    limit = hi[j] if arr[i, j] > hi[j] else lo[j]
                    first = (i, f"point {i} (t = {self.t[i]:.3f} s): joint {j + 1} {what} {arr[i, j]:.4g} "
                                f"beyond its limit {limit:.4g}")  # fmt: skip
        if first is not None:
            raise TrajectoryError(first[1])

    def acceleration(self) -> np.ndarray:
        """The spline's acceleration at each point (the larger of the two segments' ends meeting there)."""
        h = np.diff(self.t)[:, None]
        p0, p1, v0, v1 = self.q[:-1], self.q[1:], self.qd[:-1], self.qd[1:]
        a_start = (6 * (p1 - p0) / h - 4 * v0 - 2 * v1) / h  # second derivative at s = 0
        a_end = (-6 * (p1 - p0) / h + 2 * v0 + 4 * v1) / h  # at s = 1
        acc = np.zeros_like(self.q)
        acc[:-1] = a_start
        bigger = np.abs(a_end) > np.abs(acc[1:])
        acc[1:][bigger] = a_end[bigger]
        return acc
