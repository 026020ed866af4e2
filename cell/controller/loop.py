"""A model of the closed loop a TP drives, for choosing the TPs' target velocities.

Within a section the data plane commands v = (1-c1) v + c1 v_trg + c2 (p_trg - p)
on every status packet; the robot keeps the latest command of each window and
executes it at the window's end, within its acceleration limit.  A TP has
one free number per joint that matters (v_trg: p_trg is the plan's position
at the section's end), and where the robot ends up at the section's end
grows monotonically with it.  So the controller simulates the section from
the state the previous one left and picks v_trg, per joint, that brings the
robot onto the plan at the TP: a few vectorised passes over a grid of
candidates.  This takes the command latency, the window's sample-and-hold
and the acceleration limit into account, which a TP holding the plan's own
velocity ignores (that lags the plan by tens of mrad at 10 TP/s).

It needs sections several windows long; shorter ones (the fine mode) use
the midpoint rule of cell.controller.tps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_CANDIDATES = 48
_PASSES = 4


@dataclass(frozen=True)
class LoopModel:
    c1: np.ndarray  # the data plane's constants, per joint
    c2: np.ndarray
    v_max: np.ndarray  # what the data plane lets through (LimitVelocity) and the drive runs
    a_max: np.ndarray  # the drive's acceleration limit
    status_s: float = 0.002  # one status packet per joint this often
    window: int = 4  # status packets per command window

    def run(
        self,
        q: np.ndarray,
        v: np.ndarray,
        held: np.ndarray,
        tick: int,
        n: int,
        p_trg: np.ndarray,
        v_trg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """n status periods of the loop from (q, v, the command the drive holds); arrays broadcast
        over leading axes (candidates).  Returns the state at the end."""
        dt = self.status_s
        for i in range(n):
            cmd = (1.0 - self.c1) * v + self.c1 * v_trg + self.c2 * (p_trg - q)
            if (tick + i) % self.window == self.window - 1:
                held = np.broadcast_to(cmd, np.broadcast_shapes(cmd.shape, held.shape))
            goal = np.clip(held, -self.v_max, self.v_max)
            dv = np.clip(goal - v, -self.a_max * dt, self.a_max * dt)
            q = q + (v + 0.5 * dv) * dt
            v = v + dv
        return q, v, held

    def min_section_s(self) -> float:
        return 6 * self.window * self.status_s

    def fit(self, q_end: np.ndarray, t_end: np.ndarray, q0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """v_trg for each section (rows of q_end, ending at t_end s) so that the modelled robot,
        starting at (q0, v0), is on q_end at each section's end."""
        dof = q0.size
        q, v, held = q0.astype(np.float64), v0.astype(np.float64), v0.astype(np.float64)
        tick, t0 = 0, 0.0
        out = np.empty((len(t_end), dof))
        span = 4.0 * self.v_max + 1.0
        for k in range(len(t_end)):
            n = max(1, round((t_end[k] - t0) / self.status_s))
            lo, hi = -span, span
            for _ in range(_PASSES):
                cand = np.linspace(lo, hi, _CANDIDATES)  # (C, dof)
                qe, _, _ = self.run(q, v, held, tick, n, q_end[k], cand)
                # the end position grows with v_trg: take the candidates around the crossing
                below = (qe < q_end[k]).sum(axis=0)  # per joint: how many candidates fall short
                i = np.clip(below, 1, _CANDIDATES - 1)
                lo, hi = cand[i - 1, np.arange(dof)], cand[i, np.arange(dof)]
            out[k] = 0.5 * (lo + hi)
            q, v, held = self.run(q, v, held, tick, n, q_end[k], out[k])
            tick += n
            t0 = float(t_end[k])
        return out
