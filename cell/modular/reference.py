"""Reference motions for the modular arm: tool paths at a top speed, as joint trajectories (position,
velocity, acceleration at the control rate).

The tool keeps its orientation; each straight segment (and the circle as a whole) follows a
minimum-jerk time scaling, so the path starts and ends at rest with smooth accelerations.  Joint
positions come from inverse kinematics, velocities and accelerations from the tool's through the
Jacobian (qd = J^-1 xd, qdd = J^-1 (xdd - Jd qd)): exact for the path, where differencing the
inverse kinematics' answers would amplify its rounding.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import mujoco
import numpy as np

from cell.modular.arm import ModularArm
from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics

Q_HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
CYCLE_NS = 1_000_000  # the control cycle (the slides' 1 ms [A,B,C,D] cycle)
CYCLE_S = CYCLE_NS / 1e9


@dataclass(frozen=True)
class Reference:
    name: str
    t: np.ndarray  # (n,) s, one a control cycle
    q: np.ndarray  # (n, 6)
    qd: np.ndarray
    qdd: np.ndarray
    tool: np.ndarray  # (n, 3) the tool's planned position


def _min_jerk(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, rate and acceleration of the minimum-jerk scaling on s in [0, 1]."""
    return (
        10 * s**3 - 15 * s**4 + 6 * s**5,
        30 * s**2 - 60 * s**3 + 30 * s**4,
        60 * s - 180 * s**2 + 120 * s**3,
    )


def _segments(points: list[np.ndarray], speed: float, dwell_s: float) -> tuple[np.ndarray, ...]:
    """Straight segments through the points, each at the top speed at its middle, with a dwell at
    each point: the tool's position, velocity, acceleration at every cycle."""
    pos, vel, acc = [points[0][None, :]], [np.zeros((1, 3))], [np.zeros((1, 3))]
    for a, b in itertools.pairwise(points):
        length = float(np.linalg.norm(b - a))
        duration = max(1.875 * length / speed, 0.05)  # (minimum jerk peaks at 1.875 x the mean)
        s = np.arange(1, round(duration / CYCLE_S) + 1) * CYCLE_S / duration
        p, r, ra = _min_jerk(np.minimum(s, 1.0))
        d = b - a
        pos.append(a + p[:, None] * d)
        vel.append(r[:, None] * d / duration)
        acc.append(ra[:, None] * d / duration**2)
        rest = round(dwell_s / CYCLE_S)
        pos.append(np.repeat(b[None, :], rest, 0))
        vel.append(np.zeros((rest, 3)))
        acc.append(np.zeros((rest, 3)))
    return np.concatenate(pos), np.concatenate(vel), np.concatenate(acc)


def _circle(center: np.ndarray, radius: float, speed: float) -> tuple[np.ndarray, ...]:
    """Once round a horizontal circle from rest to rest: the angle on a minimum-jerk scaling."""
    duration = 1.875 * 2 * np.pi * radius / speed
    n = round(duration / CYCLE_S)
    s = np.arange(n + 1) * CYCLE_S / duration
    p, r, ra = _min_jerk(np.minimum(s, 1.0))
    th, thd, thdd = 2 * np.pi * p, 2 * np.pi * r / duration, 2 * np.pi * ra / duration**2
    c, sn = np.cos(th), np.sin(th)
    pos = center + radius * np.stack([c - 1.0, sn, np.zeros_like(c)], axis=1)
    vel = radius * np.stack([-sn * thd, c * thd, np.zeros_like(c)], axis=1)
    acc = radius * np.stack([-c * thd**2 - sn * thdd, -sn * thd**2 + c * thdd, np.zeros_like(c)], axis=1)
    return pos, vel, acc


def _to_joints(name: str, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, rot: np.ndarray) -> Reference:
    kin = Kinematics(arm_model("ur5e"))
    arm = ModularArm()
    model, data = arm.model, mujoco.MjData(arm.model)
    jp, jr = np.zeros((3, 6)), np.zeros((3, 6))
    n = len(pos)
    q, qd, qdd = np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 6))
    near = Q_HOME

    def jacobian(qk: np.ndarray) -> np.ndarray:
        data.qpos[:] = qk
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        mujoco.mj_jacSite(model, data, jp, jr, arm.tool)
        return np.vstack([jp, jr])

    for k in range(n):
        near = q[k] = kin.ik(pos[k], rot, near)
        jac = jacobian(q[k])
        qd[k] = np.linalg.solve(jac, np.concatenate([vel[k], np.zeros(3)]))
        h = 1e-6  # (J's rate along qd, by a central difference in q)
        jd_qd = (jacobian(q[k] + h * qd[k]) - jacobian(q[k] - h * qd[k])) @ qd[k] / (2 * h)
        qdd[k] = np.linalg.solve(jac, np.concatenate([acc[k], np.zeros(3)]) - jd_qd)
    return Reference(name, np.arange(n) * CYCLE_S, q, qd, qdd, pos)


def pick_and_place(speed: float = 0.5, lift: float = 0.15, across: float = 0.4) -> Reference:
    """Up, across and down, and back: a pick and a place at `speed` m/s at most (0.2 s dwells)."""
    p0, rot = arm_model("ur5e").fk(Q_HOME)
    up = p0 + np.array([0.0, 0.0, lift])
    over = up + np.array([0.0, across, 0.0])
    down = over - np.array([0.0, 0.0, lift])
    pos, vel, acc = _segments([p0, up, over, down, over, up, p0], speed, dwell_s=0.2)
    return _to_joints("pick-and-place", pos, vel, acc, rot)


def circle(radius: float = 0.1, speed: float = 0.5) -> Reference:
    """Once round a horizontal circle of `radius` through the home pose at `speed` m/s at most."""
    p0, rot = arm_model("ur5e").fk(Q_HOME)
    pos, vel, acc = _circle(p0, radius, speed)
    return _to_joints("circle", pos, vel, acc, rot)


def joint_move(q0: np.ndarray, q1: np.ndarray, speed: float) -> Reference:
    """From q0 to q1 in joint space, every joint on one minimum-jerk scaling whose fastest joint
    peaks at `speed` rad/s (at least 50 ms): the modular robot's own moves (no IK on the way)."""
    d = np.asarray(q1, float) - np.asarray(q0, float)
    duration = max(1.875 * float(np.abs(d).max()) / speed, 0.05)
    s = np.arange(round(duration / CYCLE_S) + 1) * CYCLE_S / duration
    p, r, ra = _min_jerk(np.minimum(s, 1.0))
    q = q0 + p[:, None] * d
    arm = ModularArm()
    return Reference(
        "move",
        s * duration,
        q,
        r[:, None] * d / duration,
        ra[:, None] * d / duration**2,
        np.array([arm.tool_position(qk) for qk in q]),
    )
