"""The modular arm tracking a reference: Virtual Decomposition Control over the slides' four messages
with losses and late modules, or a centralised computed-torque controller, on the MuJoCo arm.

Each 1 ms cycle starts with the modules' joints (A); the torques computed from them reach the
motors one MuJoCo step (0.25 ms, about the slides' 0.3 ms cycle) later and hold until the next
cycle's.  FDIR is the slides': no retry; a message that is lost, or comes after the deadline, is
replaced by a guess from physical continuity (data obsolescence), and counted:
- A: the master predicts the joint from its last one (q + qd T, qd);
- B: the module extrapolates its last (V_r + dV_r T, qd_r + qdd_r T; the rest held);
- C: the master holds the module's last F*_r;
- D: the module holds its last tau_r;
- a neighbour's force (where = neighbour or local): held from the cycle before.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from cell.modular.arm import ModularArm
from cell.modular.reference import CYCLE_S, Reference
from cell.modular.vdc import (
    WHERE_LOCAL,
    WHERE_MASTER,
    A,
    B,
    C,
    D,
    Gains,
    Master,
    Module,
    carried_force,
)

DELAY_STEPS = 1  # MuJoCo steps from a cycle's start to its torques acting (0.25 ms)


@dataclass(frozen=True)
class Faults:
    """loss: each message (and each neighbour's force) is lost with this probability; late_module:
    that module's answers (A and C) miss the deadline in late_share of the cycles."""

    loss: float = 0.0
    late_module: int | None = None
    late_share: float = 0.0
    seed: int = 1


@dataclass
class Tracking:
    """A run: the arm's joints and tool against the reference, every cycle."""

    name: str
    t: np.ndarray
    q: np.ndarray
    q_d: np.ndarray
    tool: np.ndarray
    tool_d: np.ndarray
    guessed: Counter = field(default_factory=Counter)  # per message kind, guesses that stood in
    messages: int = 0  # messages the cycles sent (or would have)

    @property
    def tool_error_mm(self) -> np.ndarray:
        return np.linalg.norm(self.tool - self.tool_d, axis=1) * 1e3

    @property
    def tool_error_mm_max(self) -> float:
        return float(self.tool_error_mm.max())

    @property
    def tool_error_mm_rms(self) -> float:
        return float(np.sqrt(np.mean(self.tool_error_mm**2)))

    @property
    def joint_error_rad_max(self) -> float:
        return float(np.abs(self.q - self.q_d).max())


def _record(arm: ModularArm, ref: Reference, name: str) -> Tracking:
    n = len(ref.t)
    return Tracking(name, ref.t, np.empty((n, 6)), ref.q, np.empty((n, 3)), ref.tool)


def track_vdc(
    ref: Reference,
    faults: Faults = Faults(),
    where: tuple[str, ...] = (WHERE_MASTER,) * 6,
    gains: Gains | None = None,
    believed: float = 1.0,
) -> Tracking:
    """VDC over the four messages, [C, D] computed where `where` says per module; believed: the
    modules' own mass properties as this share of the arm's (1: exact; gains.adapt > 0 adapts
    them as the arm moves)."""
    arm = ModularArm(ref.q[0])
    gains = gains or Gains()
    rng = np.random.default_rng(faults.seed)
    master = Master(arm.bodies, gains)
    modules = [Module(replace(b, inertia=b.inertia * believed), gains) for b in arm.bodies]
    run = _record(arm, ref, "vdc")
    n_mod = arm.dof
    last_a = [A(float(q), 0.0) for q in ref.q[0]]
    last_b: list[B | None] = [None] * n_mod
    last_c = [C(np.zeros(6)) for _ in range(n_mod)]
    last_d = [D(0.0) for _ in range(n_mod)]
    last_f = [np.zeros(6) for _ in range(n_mod)]  # each body's F_r of the cycle before
    tau = np.zeros(n_mod)

    def lost(module: int, kind: str) -> bool:
        late = kind in ("A", "C") and module == faults.late_module and rng.random() < faults.late_share
        gone = late or (faults.loss > 0 and rng.random() < faults.loss)
        if gone:
            run.guessed[kind] += 1
        return gone

    for k in range(len(ref.t)):
        q, qd = arm.q, arm.qd
        run.q[k], run.tool[k] = q, arm.tool_position()
        # A: every module's joint, or the master's guess of it
        a = []
        for i in range(n_mod):
            if lost(i, "A"):
                p = last_a[i]
                a.append(A(p.q + p.qd * CYCLE_S, p.qd))
            else:
                a.append(A(float(q[i]), float(qd[i])))
        last_a = a
        # B: the forward recursion, or each module's extrapolation of its last
        b_sent = master.forward(a, ref.q[k], ref.qd[k], ref.qdd[k])
        b = []
        for i in range(n_mod):
            prev = last_b[i]
            if prev is not None and lost(i, "B"):
                b.append(B(prev.qd_r + prev.qdd_r * CYCLE_S, prev.qdd_r, prev.v_r + prev.a_r * CYCLE_S,
                           prev.a_r, prev.v))  # fmt: skip
            else:
                b.append(b_sent[i])
        last_b = b
        # C: each body's required net force (the master's copy, or its last)
        c = [modules[i].net_force(b[i], CYCLE_S) for i in range(n_mod)]
        c_master = [last_c[i] if lost(i, "C") else c[i] for i in range(n_mod)]
        last_c = c_master
        # [C, D] from the tip in: by the master, or by the module with its neighbour's force
        d_master = master.backward(c_master)
        x = master.transforms
        f_now: list[np.ndarray] = [np.zeros(6)] * n_mod
        tau_r = np.empty(n_mod)
        for i in range(n_mod - 1, -1, -1):
            if where[i] == WHERE_MASTER:
                tau_r[i] = last_d[i].tau_r if lost(i, "D") else d_master[i].tau_r
                last_d[i] = D(tau_r[i])
                f_now[i] = master.forces[i]
                continue
            if i + 1 < n_mod:
                fresh = f_now[i + 1] if where[i] != WHERE_LOCAL else last_f[i + 1]
                f_next = last_f[i + 1] if lost(i, "F") else fresh
                carried = carried_force(x[i + 1], f_next)
            else:
                carried = np.zeros(6)
            f_now[i], tau_r[i] = modules[i].force_with(c[i], carried)
        last_f = f_now
        run.messages += 4 * n_mod
        new = np.array([modules[i].torque(tau_r[i], b[i], float(qd[i])) for i in range(n_mod)])
        arm.step(tau, DELAY_STEPS)
        tau = new
        arm.step(tau, round(CYCLE_S / arm.model.opt.timestep) - DELAY_STEPS)
    return run


def track_centralised(ref: Reference, kp: float = 900.0, kv: float = 60.0) -> Tracking:
    """The slides' centralised control: one computer with every joint computes the torques of the
    whole arm (computed torque, MuJoCo's own inverse dynamics, PD on the joint errors)."""
    arm = ModularArm(ref.q[0])
    run = _record(arm, ref, "centralised")
    limit = np.array([b.torque_max for b in arm.bodies])
    tau = np.zeros(arm.dof)
    for k in range(len(ref.t)):
        q, qd = arm.q, arm.qd
        run.q[k], run.tool[k] = q, arm.tool_position()
        qdd = ref.qdd[k] + kv * (ref.qd[k] - qd) + kp * (ref.q[k] - q)
        new = np.clip(arm.inverse_dynamics(q, qd, qdd), -limit, limit)
        arm.step(tau, DELAY_STEPS)
        tau = new
        arm.step(tau, round(CYCLE_S / arm.model.opt.timestep) - DELAY_STEPS)
    return run
