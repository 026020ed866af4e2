"""Virtual Decomposition Control (W.-H. Zhu, "Virtual Decomposition Control: Toward Hyper Degrees of
Freedom Robots", Springer 2010), distributed as seed 002's slides distribute it: the master runs
the kinematics and the force propagation, each module the dynamics of its own rigid body.

One control cycle, the four messages of the slides (docs/modular.md has the equations):
- A, module i -> master: its joint position and velocity (q_i, qd_i);
- B, master -> module i: its required joint velocity and acceleration (qd_r,i, qdd_r,i), and its
  rigid body's required velocity, required acceleration and actual velocity in its own frame
  (V_r,i, dV_r,i, V_i: the forward recursion over the chain);
- C, module i -> master: the required net force/moment of its rigid body, F*_r,i, computed from
  its own inertia (dynamics, gravity, and velocity feedback in its body frame);
- D, master -> module i: its required joint torque tau_r,i = z^T F_r,i, F_r,i = F*_r,i plus the
  force its outboard neighbour's body needs, propagated from the tip (the backward recursion).
The module adds its motor's part (rotor inertia, friction) and a joint velocity feedback, and
drives its motor with the sum.

[C, D] may also be computed by a module itself (WHERE_LOCAL: with its outboard neighbour's force of
the cycle before) or by the module with its neighbour's force of this cycle (WHERE_NEIGHBOUR),
instead of the master (WHERE_MASTER): the same arithmetic, other messages.

All of it is pure (no sockets, no clock): cell.modular.loop runs it against the MuJoCo arm with
messages lost or late, cell.snp carries it between processes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cell.modular.arm import AXIS, GRAVITY, Body, crf, crm, skew

WHERE_MASTER, WHERE_NEIGHBOUR, WHERE_LOCAL = "master", "neighbour", "local"


@dataclass(frozen=True)
class Gains:
    """lam: joint position error into the required velocity (1/s); body_rot, body_lin: the velocity
    feedback of each rigid body in its frame, per kg of it (N m s/rad, N s/m); joint: the module's
    joint velocity feedback for the biggest motor (150 N m; N m s/rad), smaller ones in proportion."""

    lam: float = 40.0
    body_rot: float = 2.0
    body_lin: float = 40.0
    joint: float = 30.0
    adapt: float = 0.0  # the inertial parameters' adaptation gain (0: none)


@dataclass(frozen=True)
class A:
    q: float
    qd: float


@dataclass(frozen=True)
class B:
    qd_r: float
    qdd_r: float
    v_r: np.ndarray  # (6,) the module's body, its frame
    a_r: np.ndarray
    v: np.ndarray


@dataclass(frozen=True)
class C:
    f_star: np.ndarray  # (6,) required net force/moment [n; f] of the module's body, its frame


@dataclass(frozen=True)
class D:
    tau_r: float


@dataclass
class Master:
    """The master's half: the forward recursion (A -> B) and the backward one (C -> D)."""

    bodies: tuple[Body, ...]
    gains: Gains = field(default_factory=Gains)
    transforms: list[np.ndarray] = field(default_factory=list)  # this cycle's ^iX_{i-1}
    forces: list[np.ndarray] = field(default_factory=list)  # this cycle's F_r,i, from backward()

    def forward(self, a: list[A], q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray) -> list[B]:
        """B for every module from their A and the reference (position, velocity, acceleration)."""
        carry = BASE
        self.transforms = []
        out = []
        for i, body in enumerate(self.bodies):
            b, x, carry = forward_step(body, self.gains.lam, a[i], q_d[i], qd_d[i], qdd_d[i], carry)
            self.transforms.append(x)
            out.append(b)
        return out

    def backward(self, c: list[C]) -> list[D]:
        """D for every module: each body's required force plus what it carries for the bodies out to
        the tip, projected on its joint."""
        self.forces = [np.zeros(6)] * len(c)
        for i in range(len(c) - 1, -1, -1):
            outboard = carried_force(self.transforms[i + 1], self.forces[i + 1]) if i + 1 < len(c) else 0.0
            self.forces[i] = c[i].f_star + outboard
        return [D(float(AXIS @ f)) for f in self.forces]


@dataclass(frozen=True)
class Carry:
    """What the forward recursion carries from a body to the next out, in the body's frame: its
    velocity, required velocity and required acceleration."""

    v: np.ndarray
    v_r: np.ndarray
    a_r: np.ndarray


BASE = Carry(np.zeros(6), np.zeros(6), np.concatenate([np.zeros(3), -GRAVITY]))  # (gravity: the base's
# upward acceleration)


def forward_step(
    body: Body, lam: float, a: A, q_d: float, qd_d: float, qdd_d: float, parent: Carry
) -> tuple[B, np.ndarray, Carry]:
    """One body of the forward recursion: its B, its transform ^iX_{i-1} and what it carries on."""
    q, qd = a.q, a.qd
    qd_r = qd_d + lam * (q_d - q)
    qdd_r = qdd_d + lam * (qd_d - qd)
    x = body.transform(q)
    v = x @ parent.v + AXIS * qd
    carried = x @ parent.v_r
    v_r = carried + AXIS * qd_r
    # d/dt of X V_r,i-1 + z qd_r: X's rate is -(z qd) x X
    a_r = x @ parent.a_r + AXIS * qdd_r + crm(carried) @ (AXIS * qd)
    return B(qd_r, qdd_r, v_r, a_r, v), x, Carry(v, v_r, a_r)


def carried_force(x_next: np.ndarray, f_next: np.ndarray) -> np.ndarray:
    """The force module i+1's body needs from module i's, in module i's frame (^{i+1}X_i^T f)."""
    return x_next.T @ f_next


def inertia_of(theta: np.ndarray) -> np.ndarray:
    """The 6x6 spatial inertia of a body's ten inertial parameters theta = [m, m c (3), the
    rotational inertia about the frame's origin: xx, yy, zz, xy, xz, yz]: linear in theta."""
    m, mc, (xx, yy, zz, xy, xz, yz) = theta[0], theta[1:4], theta[4:10]
    out = np.zeros((6, 6))
    out[:3, :3] = [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]
    out[:3, 3:] = skew(mc)
    out[3:, :3] = skew(mc).T
    out[3:, 3:] = m * np.eye(3)
    return out


def theta_of(inertia: np.ndarray) -> np.ndarray:
    """inertia_of's inverse."""
    rot, mc = inertia[:3, :3], np.array([inertia[2, 4], inertia[0, 5], inertia[1, 3]])
    return np.array([inertia[5, 5], *mc, rot[0, 0], rot[1, 1], rot[2, 2], rot[0, 1], rot[0, 2], rot[1, 2]])


_BASIS = np.stack([inertia_of(np.eye(10)[k]) for k in range(10)])  # d inertia / d theta_k


@dataclass
class Module:
    """A module's half: its body's required net force (B -> C) and its motor torque (D -> tau).

    With gains.adapt > 0 the module adapts its body's inertial parameters as it runs (VDC's
    parameter adaptation: F*_r = Y theta + K (V_r - V), theta' = adapt Y^T (V_r - V), Y the
    regressor of I dV_r + V x* I V_r in theta), each kept within bounds of where it started (the
    projection of Zhu's law: mass properties stay physical)."""

    body: Body
    gains: Gains = field(default_factory=Gains)
    theta: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.theta = theta_of(self.body.inertia)
        m0 = float(self.theta[0])
        # how far each parameter may move: 4x its start, and at least what a body this heavy could
        # have (its mass 10 cm off the axis, 1 dm^2 of it in inertia)
        self.bound = 4.0 * np.abs(self.theta) + m0 * np.array([1.0, *[0.1] * 3, *[0.01] * 6])
        self.mass0 = m0

    def net_force(self, b: B, dt: float = 0.0) -> C:
        """F*_r = I dV_r + V x* I V_r + K (V_r - V): the body's dynamics (gravity included through
        the base's acceleration) and its velocity feedback in its own frame; with adaptation, the
        inertial parameters moved on by dt of the adaptation law."""
        inertia = inertia_of(self.theta) if self.gains.adapt > 0 else self.body.inertia
        mass = self.body.inertia[5, 5]
        k = np.concatenate([np.full(3, self.gains.body_rot * mass), np.full(3, self.gains.body_lin * mass)])
        f = inertia @ b.a_r + crf(b.v) @ (inertia @ b.v_r) + k * (b.v_r - b.v)
        if self.gains.adapt > 0 and dt > 0:
            y = _BASIS @ b.a_r + np.einsum("ij,kjl,l->ki", crf(b.v), _BASIS, b.v_r)  # (10, 6): Y^T
            step = self.gains.adapt * dt * (y @ (b.v_r - b.v))
            self.theta = np.clip(self.theta + step, -self.bound, self.bound)
            self.theta[0] = max(self.theta[0], 0.25 * self.mass0)
        return C(f)

    def torque(self, tau_r: float, b: B, qd: float) -> float:
        """The motor's torque: the chain's share, the motor's own (rotor, friction) and the joint's
        velocity feedback, within the motor's limit."""
        body = self.body
        tau = (
            tau_r
            + body.armature * b.qdd_r
            + body.damping * b.qd_r
            + self.gains.joint * body.torque_max / 150.0 * (b.qd_r - qd)
        )
        return float(np.clip(tau, -body.torque_max, body.torque_max))

    def force_with(self, c: C, carried: np.ndarray) -> tuple[np.ndarray, float]:
        """[C, D] here ([C, D] by the module or with its neighbour): F = F* + what the outboard
        body needs, and its projection on the joint."""
        f = c.f_star + carried
        return f, float(AXIS @ f)
