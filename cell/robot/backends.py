"""How the robots of a group move: a kinematic model (fleets), MuJoCo physics (one per robot), or a
real UR controller's own servos (RemoteArm: its state read over RTDE).

Each takes velocity references from the same Drives (window semantics and
limits) and exposes q and qd, (robots, dof) arrays, after each step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import mujoco
import numpy as np

from cell.robot.arm import ArmModel
from cell.robot.drive import Drives


class Arms(Protocol):
    """What a group's backend is: its drives, and q and qd after each step."""

    drives: Drives
    q: np.ndarray
    qd: np.ndarray

    def step(self, dt: float) -> None: ...


class KinematicArms:
    """Joints move exactly as their drives do: the fast model for fleets of hundreds of robots."""

    def __init__(self, arm: ArmModel, q0: np.ndarray, watchdog: int) -> None:
        lim = arm.limits
        self.drives = Drives(len(q0), lim.v_max, lim.a_max, watchdog)
        self.q_min, self.q_max = lim.q_min, lim.q_max
        self.q = np.array(q0, np.float64)
        self.qd = self.drives.velocity
        self.limit_hits = 0

    def step(self, dt: float) -> None:
        self.q += self.drives.step(dt) * dt
        out = (self.q < self.q_min) | (self.q > self.q_max)
        if out.any():  # a joint at its end stop halts there
            self.limit_hits += int(out.sum())
            np.clip(self.q, self.q_min, self.q_max, out=self.q)
            self.drives.velocity[out] = 0.0
            self.drives.target[out] = 0.0


class MujocoArms:
    """Each robot simulated by MuJoCo: velocity-mode servos on the arm's own model.

    The drive's velocity reference is integrated into a position reference and
    fed forward, ctrl = q_ref + (kv/kp) v_ref, so the servo tracks velocity
    without the lag of a plain position servo; gravity is compensated by the model
    (gravcomp), and so are inertia, Coriolis forces and joint friction, as an
    industrial drive's model-based feed-forward does: tau_ff = M(q) a_ref +
    c(q, v) + damping v_ref.  Without it the servo lags its reference whenever
    the arm accelerates or turns, an error no controller upstream can see coming.
    In an offline loop of the accuracy bench's joint moves (planner, TPs, the
    real pipeline, these drives) the tool path error at TPs was 0.93 mm max,
    0.32 mm median without feed-forward; 0.43 / 0.20 with M a; 0.18 / 0.04
    once the servo also aimed at the reference of the step's start (it aimed a
    step ahead, h v) and Coriolis forces were fed forward.
    """

    def __init__(self, arm: ArmModel, q0: np.ndarray, watchdog: int) -> None:
        m = arm.model
        lim = arm.limits
        self.model = m
        self.drives = Drives(len(q0), lim.v_max, lim.a_max, watchdog)
        self.q_min, self.q_max = lim.q_min, lim.q_max
        self.data = [mujoco.MjData(m) for _ in range(len(q0))]
        for d, q in zip(self.data, q0, strict=True):
            d.qpos[:] = q
            d.ctrl[:] = q
            mujoco.mj_forward(m, d)
        self.q_ref = np.array(q0, np.float64)
        self.feedforward = -m.actuator_biasprm[:, 2] / m.actuator_gainprm[:, 0]  # kv / kp
        self.damping = m.dof_damping.copy()
        self._tau = np.zeros(m.nv)
        self.q = np.array(q0, np.float64)
        self.qd = np.zeros_like(self.q)
        self.limit_hits = 0

    def step(self, dt: float) -> None:
        h = self.model.opt.timestep
        steps = max(1, round(dt / h))
        drives, tau = self.drives, self._tau
        for _ in range(steps):
            before = drives.velocity.copy()
            # the servo acts on the state at the step's start, so it aims at the reference there (aiming
            # at the step's end put the arm a step, h v, ahead of its drive); the velocity term is
            # evaluated at the step's end, as the implicit integrator evaluates damping
            ctrl = self.q_ref + self.feedforward * drives.velocity
            v = drives.step(h)
            accel = (drives.velocity - before) / h
            ctrl += self.feedforward * (drives.velocity - before)
            self.q_ref += v * h
            np.minimum(np.maximum(self.q_ref, self.q_min, out=self.q_ref), self.q_max, out=self.q_ref)
            for i, d in enumerate(self.data):
                d.ctrl[:] = ctrl[i]
                # M, Coriolis and centrifugal forces (qfrc_bias less gravity, which gravcomp takes) from the
                # last step's pass: no extra one
                mujoco.mj_mulM(self.model, d, tau, accel[i])
                tau += d.qfrc_bias
                tau -= d.qfrc_gravcomp
                d.qfrc_applied[:] = tau + self.damping * drives.velocity[i]
                mujoco.mj_step(self.model, d)
        for i, d in enumerate(self.data):
            self.q[i] = d.qpos
            self.qd[i] = d.qvel


def joint_torques(d: mujoco.MjData, dof: int) -> tuple[np.ndarray, np.ndarray]:
    """A MuJoCo arm's joint torques (N m) after its last step: what its drives apply (the servo's
    actuator force, the model-based feed-forward and the gravity compensation: RTDE's target_moment
    and actual_current_as_torque), and what the joints bear beyond the arm's own dynamics (the
    constraints': contacts and end stops, as URScript's get_joint_torques() reports, negated as the
    drives' share of it)."""
    motor = d.qfrc_actuator[:dof] + d.qfrc_applied[:dof] + d.qfrc_gravcomp[:dof]
    return motor.copy(), -d.qfrc_constraint[:dof]


class RemoteArm:
    """A UR controller elsewhere (cell.ur.remote): q and qd are what its RTDE says, and the drives
    only keep the command windows, the watchdog and the holds; the controller's own servos move it."""

    def __init__(self, arm: ArmModel, q0: np.ndarray, watchdog: int) -> None:
        lim = arm.limits
        self.drives = Drives(len(q0), lim.v_max, lim.a_max, watchdog)
        self.q = np.array(q0, np.float64)
        self.qd = np.zeros_like(self.q)
        self.limit_hits = 0

    def step(self, dt: float) -> None:
        """(The arm moves by itself: its state comes in with its RTDE packages.)"""


BACKENDS: dict[str, Callable[[ArmModel, np.ndarray, int], Arms]] = {
    "kinematic": KinematicArms,
    "mujoco": MujocoArms,
    "ur": RemoteArm,
}
