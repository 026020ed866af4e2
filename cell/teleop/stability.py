"""Why the gains are stable: the experiment's vertical axis as a linear sampled-data system.

Each tip is a mass (the arm's operational-space inertia at the start pose,
from MuJoCo) with the arm's viscous friction.  The operator's hand Z_l acts
on the local tip and the object Z_r (in contact: its spring and damper in
series with the contact's stiffness) on the remote tip, continuously; the
controllers of cell.teleop.law act on samples every T = 1 ms, through a
zero-order hold.  A side's own measurements are current, the peer's are d
periods old: d = 1 on the link itself, plus the added delay.  The closed
loop is linear in the state of both tips and its last d samples; it is
stable when every eigenvalue of the map from one period to the next lies
inside the unit circle.  `spectral_radius` is that largest magnitude.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mujoco
import numpy as np

from cell.teleop.law import Gains, Mode
from cell.teleop.model import CONTACT_STIFFNESS, OBJECTS, Arm
from cell.teleop.operator import Operator
from cell.teleop.side import PERIOD_S


@dataclass(frozen=True)
class Plant:
    mass: float  # kg: the tip's apparent mass along z
    friction: float  # N s/m: the joints' viscous friction seen at the tip
    hand_k: float  # N/m: Z_l
    hand_b: float  # N s/m
    object_k: float  # N/m: Z_r in contact, with the contact in series
    object_b: float  # N s/m


@functools.cache  # (a MuJoCo model built once, not once per delay a scan tries)
def tip_inertia() -> tuple[float, float]:
    """The arm's apparent mass and viscous friction along z at the start pose (MuJoCo's model)."""
    arm = Arm()
    m, d = arm.model, arm.data
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    jac = arm.jacobian()[1:2]  # the z row
    lam = 1.0 / float((jac @ np.linalg.solve(full, jac.T))[0, 0])
    # joint damping B maps to the tip as (J B^-1 J^T)^-1
    damping = np.diag(m.dof_damping[:2])
    fric = 1.0 / float((jac @ np.linalg.solve(damping, jac.T))[0, 0])
    return lam, fric


def plant(obj: str) -> Plant:
    mass, fric = tip_inertia()
    spec, op = OBJECTS[obj], Operator(np.zeros(2))
    k = 1.0 / (1.0 / spec.stiffness + 1.0 / CONTACT_STIFFNESS)
    return Plant(mass, fric, op.stiffness, op.damping, k, spec.damping)


def _expm(a: np.ndarray) -> np.ndarray:
    """exp(a) by scaling and squaring a Taylor series (the matrices here are small and tame)."""
    s = max(0, int(np.ceil(np.log2(max(float(np.linalg.norm(a, 1)), 1e-12)))) + 1)
    a = a / 2**s
    out, term = np.eye(len(a)), np.eye(len(a))
    for i in range(1, 20):
        term = term @ a / i
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


def closed_loop(p: Plant, g: Gains, mode: Mode, delay_periods: int, period: float = PERIOD_S) -> np.ndarray:
    """The map from one period's augmented state to the next: [s_k, s_k-1, ..., s_k-d], s = (x_l, v_l,
    x_r, v_r) as deviations from the contact equilibrium."""
    d = delay_periods
    if d < 1:
        raise ValueError("the peer's samples are at least one period old")
    m = p.mass
    # continuous: ds/dt = A s + B u, u = (u_l, u_r)
    a = np.array([
        [0, 1, 0, 0],
        [-p.hand_k / m, -(p.hand_b + p.friction) / m, 0, 0],
        [0, 0, 0, 1],
        [0, 0, -p.object_k / m, -(p.object_b + p.friction) / m],
    ])  # fmt: skip
    b = np.array([[0, 0], [1 / m, 0], [0, 0], [0, 1 / m]])
    big = np.zeros((6, 6))
    big[:4, :4], big[:4, 4:] = a * period, b * period
    e = _expm(big)
    phi, gam = e[:4, :4], e[:4, 4:]
    # the sampled forces as rows on s
    f_l = np.array([-p.hand_k, -p.hand_b, 0, 0])
    f_r = np.array([0, 0, -p.object_k, -p.object_b])
    x_l, v_l, x_r, v_r = np.eye(4)
    k_fl = g.k_fl if mode == Mode.MODIFIED else 0.0
    k_fr = g.k_fr if mode == Mode.MODIFIED else 0.0
    reflect = 0.0 if mode == Mode.UNILATERAL else 1.0
    # u = K0 s_k + Kd s_k-d
    k0 = np.vstack([k_fl * f_l - g.d_l * v_l, -g.kp * x_r - g.dp * v_r + k_fr * f_r])
    kd = np.vstack([reflect * (1 + k_fl) * f_r, g.kp * x_l + g.dp * v_l + k_fr * f_l])
    n = 4 * (d + 1)
    m_out = np.zeros((n, n))
    m_out[:4, :4] = phi + gam @ k0
    m_out[:4, 4 * d : 4 * d + 4] += gam @ kd
    for i in range(d):  # shift the history
        m_out[4 * (i + 1) : 4 * (i + 2), 4 * i : 4 * i + 4] = np.eye(4)
    return m_out


def spectral_radius(
    obj: str, g: Gains | None = None, mode: Mode = Mode.MODIFIED, delay_s: float = 0.0
) -> float:
    d = 1 + round(delay_s / PERIOD_S)
    return float(np.abs(np.linalg.eigvals(closed_loop(plant(obj), g or Gains(), mode, d))).max())


def critical_delay_ms(
    obj: str, g: Gains | None = None, mode: Mode = Mode.MODIFIED, up_to_ms: int = 50
) -> int | None:
    """The smallest added delay (whole ms) at which the loop is no longer stable; None: stable up to
    `up_to_ms`."""
    for ms in range(up_to_ms + 1):
        if spectral_radius(obj, g, mode, ms / 1e3) >= 1.0:
            return ms
    return None
