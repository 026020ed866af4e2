"""The bilateral control law of the Responsive Processor paper's Fig. 14, in task space.

Forces are what the outside exerts on each tip, as each tip's sensor measures
it: f_l from the operator on the local tip, f_r from the object on the remote
one.  Transparency is f_l + f_r = 0 (the paper's eq. 2: minimise |F_l + F_r|):
the operator feels exactly what the object does.  Primes are the peer's
values as the last data packet brought them.

    local  (force reflection + local force loop):
        u_l = f_r' + K_fl (f_l + f_r') - D_l v_l
    remote (position controller K_p + remote force loop):
        u_r = K_p (x_l' - x_r) + D_p (v_l' - v_r) + K_fr (f_l' + f_r)

At rest the local arm's law leaves (1 + K_fl)(f_l + f_r') = 0, so the force
error vanishes whatever the object; the remote's position error is then
f_r / K_p (K_fr scales it down while the force error is not yet zero).  The
local loop divides the arm's inertia and leftover friction as the operator
feels them by (1 + K_fl); the remote loop does the same for the remote arm, so
it gives way to a stiff object instead of bouncing on it.  K_fl = K_fr = 0 is
the conventional force-reflecting servo; "unilateral" reflects no force (the
operator feels only the local arm).  Gains and their stability: docs/teleop.md
and cell.teleop.stability.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Mode(IntEnum):
    """The control state, changed with a MODE event on the event link."""

    MODIFIED = 0  # Fig. 14: force loops on both sides
    CONVENTIONAL = 1  # force-reflecting servo: K_fl = K_fr = 0
    UNILATERAL = 2  # position following only, no force reflected


@dataclass(frozen=True)
class Gains:
    kp: float = 1500.0  # N/m: remote position controller K_p
    dp: float = 30.0  # N s/m: its damping on the velocity error
    k_fl: float = 1.0  # local force controller K_fl
    k_fr: float = 0.5  # remote force controller K_fr
    d_l: float = 4.0  # N s/m: local damping (the operator's hand adds its own)
    hold_kp: float = 1500.0  # N/m: holding a position while stopped
    hold_dp: float = 40.0  # N s/m
    brake_kp: float = 5000.0  # N/m: the e-stop's brake, holding where the arm was
    brake_dp: float = 90.0  # N s/m (about critical on the tip's 0.36 kg)
    u_max: float = 40.0  # N: the largest tip force either arm is asked for


def local_force(g: Gains, mode: Mode, v_l: np.ndarray, f_l: np.ndarray, f_r_peer: np.ndarray) -> np.ndarray:
    if mode == Mode.UNILATERAL:
        u = -g.d_l * v_l
    else:
        k_fl = g.k_fl if mode == Mode.MODIFIED else 0.0
        u = f_r_peer + k_fl * (f_l + f_r_peer) - g.d_l * v_l
    return np.clip(u, -g.u_max, g.u_max)


def remote_force(
    g: Gains,
    mode: Mode,
    x_r: np.ndarray,
    v_r: np.ndarray,
    f_r: np.ndarray,
    x_l_peer: np.ndarray,
    v_l_peer: np.ndarray,
    f_l_peer: np.ndarray,
) -> np.ndarray:
    u = g.kp * (x_l_peer - x_r) + g.dp * (v_l_peer - v_r)
    if mode == Mode.MODIFIED:
        u = u + g.k_fr * (f_l_peer + f_r)
    return np.clip(u, -g.u_max, g.u_max)


def hold_force(g: Gains, x: np.ndarray, v: np.ndarray, at: np.ndarray, brake: bool = False) -> np.ndarray:
    """Holding still at `at`: what a stopped side does; `brake`: the e-stop's stiffer hold."""
    kp, dp = (g.brake_kp, g.brake_dp) if brake else (g.hold_kp, g.hold_dp)
    return np.clip(kp * (at - x) - dp * v, -g.u_max, g.u_max)
