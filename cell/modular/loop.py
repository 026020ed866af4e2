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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from time import perf_counter_ns
from typing import Protocol, TypeVar

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

M = TypeVar("M", A, B, C, D)  # one of the four messages
DELAY_STEPS = 1  # MuJoCo steps from a cycle's start to its torques acting (0.25 ms)


@dataclass(frozen=True)
class Faults:
    """loss: each message (and each neighbour's force) is lost with this probability; late_module:
    that module's answers (A and C) miss the deadline in late_share of the cycles."""

    loss: float = 0.0
    late_module: int | None = None
    late_share: float = 0.0
    seed: int = 1


class Link(Protocol):
    """How the four messages cross between modules and master: what the receiver gets (None: lost on
    the way).  `InMemory` hands them over as they are; cell.modular.wire.SnpLink carries them as
    SnP-MrT packets over UDP sockets."""

    def new_cycle(self) -> None: ...
    def a(self, i: int, a: A) -> A | None: ...
    def b(self, i: int, b: B) -> B | None: ...
    def c(self, i: int, c: C) -> C | None: ...
    def d(self, i: int, d: D) -> D | None: ...


class InMemory:
    """The messages as they are (the figures' default: the loss is the Faults')."""

    def new_cycle(self) -> None:
        pass

    def a(self, i: int, a: A) -> A:
        return a

    def b(self, i: int, b: B) -> B:
        return b

    def c(self, i: int, c: C) -> C:
        return c

    def d(self, i: int, d: D) -> D:
        return d


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


class VdcArm:
    """The MuJoCo arm under VDC over the four messages, one 1 ms cycle at a time (`cycle`): the
    closed loop of `track_vdc` and of the `modular` service.

    A module in `unplugged` is off the network: every message of its own is guessed (counted as
    any loss is) and its motor holds its joint on its brake (a stiff joint-local PD about where it
    was unplugged), as a module without its master does."""

    BRAKE_KP, BRAKE_KD = 3000.0, 60.0  # N m/rad, N m s/rad (within each motor's limit)

    def __init__(
        self,
        q0: np.ndarray,
        faults: Faults = Faults(),
        where: tuple[str, ...] = (WHERE_MASTER,) * 6,
        gains: Gains | None = None,
        believed: float = 1.0,
        link: Link | None = None,
    ) -> None:
        self.arm = arm = ModularArm(q0)
        self.link = link or InMemory()
        self.faults, self.where = faults, where
        gains = gains or Gains()
        self.rng = np.random.default_rng(faults.seed)
        self.master = Master(arm.bodies, gains)
        self.modules = [Module(replace(b, inertia=b.inertia * believed), gains) for b in arm.bodies]
        n = self.dof = arm.dof
        self.guessed: Counter = Counter()  # per message kind
        self.guessed_by = np.zeros(n, dtype=np.int64)  # per module
        self.messages = 0
        self.phase_ns = np.zeros(4)  # the last cycle's A, B, C, D arithmetic (D: with the torques)
        self.a_lost = np.zeros(n, dtype=bool)  # this cycle's: whose A the master guessed
        self.unplugged: dict[int, float] = {}  # module -> the joint position its brake holds
        self.last_a = [A(float(q), 0.0) for q in q0]
        self.last_b: Sequence[B | None] = [None] * n
        self.last_c = [C(np.zeros(6)) for _ in range(n)]
        self.last_d = [D(0.0) for _ in range(n)]
        self.last_f = [np.zeros(6) for _ in range(n)]  # each body's F_r of the cycle before
        self.tau = np.zeros(n)
        self.limit = np.array([b.torque_max for b in arm.bodies])

    def lost(self, module: int, kind: str) -> bool:
        f = self.faults
        late = kind in ("A", "C") and module == f.late_module and self.rng.random() < f.late_share
        gone = late or (f.loss > 0 and self.rng.random() < f.loss) or module in self.unplugged
        if gone:
            self.count_guess(module, kind)
        return gone

    def count_guess(self, module: int, kind: str) -> None:
        self.guessed[kind] += 1
        self.guessed_by[module] += 1

    def via(self, module: int, kind: str, message: M, send: Callable[[int, M], M | None]) -> M | None:
        """The message as its receiver gets it through the link; None if lost (by the faults, or by
        the link on the way), counted as a guess."""
        if self.lost(module, kind):
            return None
        got = send(module, message)
        if got is None:
            self.count_guess(module, kind)
        return got

    def unplug(self, module: int) -> None:
        self.unplugged[module] = float(self.arm.data.qpos[module])

    def plug(self, module: int) -> None:
        self.unplugged.pop(module, None)

    def cycle(self, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray) -> None:
        """One cycle toward the reference (q_d, qd_d, qdd_d): A, B, C, D, and the arm stepped to the
        next cycle's start (its torques act one MuJoCo step after the cycle starts)."""
        arm, n_mod, lost, where = self.arm, self.dof, self.lost, self.where
        master, modules = self.master, self.modules
        t_a = perf_counter_ns()
        link = self.link
        link.new_cycle()
        q, qd = arm.q, arm.qd
        # A: every module's joint, or the master's guess of it
        a = []
        for i in range(n_mod):
            got = self.via(i, "A", A(float(q[i]), float(qd[i])), link.a)
            self.a_lost[i] = got is None
            if got is None:
                p = self.last_a[i]
                a.append(A(p.q + p.qd * CYCLE_S, p.qd))
            else:
                a.append(got)
        self.last_a = a
        t_b = perf_counter_ns()
        # B: the forward recursion, or each module's extrapolation of its last
        b_sent = master.forward(a, q_d, qd_d, qdd_d)
        b = []
        for i in range(n_mod):
            prev = self.last_b[i]
            got_b = link.b(i, b_sent[i]) if prev is None else self.via(i, "B", b_sent[i], link.b)
            if got_b is None and prev is not None:
                b.append(B(prev.qd_r + prev.qdd_r * CYCLE_S, prev.qdd_r, prev.v_r + prev.a_r * CYCLE_S,
                           prev.a_r, prev.v))  # fmt: skip
            else:
                b.append(got_b if got_b is not None else b_sent[i])
        self.last_b = b
        t_c = perf_counter_ns()
        # C: each body's required net force (the master's copy, or its last)
        c = [modules[i].net_force(b[i], CYCLE_S) for i in range(n_mod)]
        c_master = [
            self.last_c[i] if (got_c := self.via(i, "C", c[i], link.c)) is None else got_c
            for i in range(n_mod)
        ]
        self.last_c = c_master
        t_d = perf_counter_ns()
        # [C, D] from the tip in: by the master, or by the module with its neighbour's force
        d_master = master.backward(c_master)
        x = master.transforms
        f_now: list[np.ndarray] = [np.zeros(6)] * n_mod
        tau_r = np.empty(n_mod)
        last_d, last_f = self.last_d, self.last_f
        for i in range(n_mod - 1, -1, -1):
            if where[i] == WHERE_MASTER:
                got_d = self.via(i, "D", d_master[i], link.d)
                tau_r[i] = last_d[i].tau_r if got_d is None else got_d.tau_r
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
        self.last_f = f_now
        self.messages += 4 * n_mod
        new = np.array([modules[i].torque(tau_r[i], b[i], float(qd[i])) for i in range(n_mod)])
        for i, hold in self.unplugged.items():  # (its brake, not the network's torque)
            brake = self.BRAKE_KP * (hold - q[i]) - self.BRAKE_KD * qd[i]
            new[i] = float(np.clip(brake, -self.limit[i], self.limit[i]))
        self.phase_ns[:] = (t_b - t_a, t_c - t_b, t_d - t_c, perf_counter_ns() - t_d)
        arm.step(self.tau, DELAY_STEPS)
        self.tau = new
        arm.step(self.tau, round(CYCLE_S / arm.model.opt.timestep) - DELAY_STEPS)


def track_vdc(
    ref: Reference,
    faults: Faults = Faults(),
    where: tuple[str, ...] = (WHERE_MASTER,) * 6,
    gains: Gains | None = None,
    believed: float = 1.0,
    link: Link | None = None,
) -> Tracking:
    """VDC over the four messages, [C, D] computed where `where` says per module; believed: the
    modules' own mass properties as this share of the arm's (1: exact; gains.adapt > 0 adapts
    them as the arm moves); link: how the messages cross (default: in memory)."""
    vdc = VdcArm(ref.q[0], faults, where, gains, believed, link)
    run = _record(vdc.arm, ref, "vdc")
    for k in range(len(ref.t)):
        run.q[k], run.tool[k] = vdc.arm.q, vdc.arm.tool_position()
        vdc.cycle(ref.q[k], ref.qd[k], ref.qdd[k])
    run.guessed, run.messages = vdc.guessed, vdc.messages
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
