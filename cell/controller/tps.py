"""A planned motion as trajectory points (TPs): what the data plane's tables hold.

Section k of a motion ends at t_k; its TP holds the planned joint positions
there and a feed-forward velocity.  The data plane commands, per packet,

    v = v_ff + (c2 / c1) (p_k - p)      (the steady state of Algorithm 2's P-controller)

so with v_ff = (p_k - p_{k-1}) / d_k, the mean velocity of the section, the
robot would run ahead of the plan by the term (c2 / c1) (p_k - p_plan(t)),
which is large early in a section.  The controller subtracts its value at the
section's midpoint: v_ff = mean - (c2 / c1) (p_k - p_plan(mid)).  Then the
correction averages out over each section and the robot is on the plan at
every TP (the accuracy bench measures how close).  The last TP holds the end
position (velocity 0, a self-loop) so a finished robot stays put.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cell.controller.loop import LoopModel, LoopTrace
from cell.trajectory.motion import Motion


@dataclass(frozen=True)
class Sections:
    """A motion cut into TP sections, times relative to the motion's start (s)."""

    t_end: np.ndarray  # (n,) end of each section; the last is the motion's end
    duration: np.ndarray  # (n,) section durations (the last may be shorter)
    q: np.ndarray  # (n, dof) planned positions at t_end
    v_ff: np.ndarray  # (n, dof) the TPs' target velocities (feed-forward, see above)
    q_plan_v: np.ndarray  # (n, dof) planned velocities at t_end (for predictions)
    trace: LoopTrace | None = None  # the loop model's robot on the way (fitted TPs only)
    p_trg: np.ndarray | None = None  # (n, dof) the TPs' positions, if not q (LoopModel.tp_positions)

    def __len__(self) -> int:
        return int(self.t_end.size)


def _knotted(knots: np.ndarray, duration: float, d: float, grid_s: float) -> np.ndarray:
    """Section ends on a motion's knots (a trajectory's points, on the robot's status grid), about d
    apart: of dense knots, the last within d of the previous end; a gap up to 1.25 d is one section,
    a longer one split evenly.  The robot is on the plan at every section's end, so at the
    trajectory's own points when they are no denser than the TPs."""

    def snap(t: float) -> float:
        return min(duration, round(t / grid_s) * grid_s) if grid_s > 0 else t

    ends: list[float] = []
    last, best = 0.0, None
    inner = [snap(k) for k in knots[(knots > 0) & (knots < duration)].tolist()]
    for k in [*inner, duration]:
        final = k >= duration
        if k - last <= d + 1e-9 and not final:
            best = k  # (a later knot may still be within d)
            continue
        if best is not None and best - last >= 0.5 * d:
            ends.append(best)
            last = best
            if k - last <= d + 1e-9 and not final:
                best = k
                continue
        best = None
        gap = k - last
        if gap <= 1e-9:
            continue
        m = max(1, math.ceil(gap / (1.25 * d) - 1e-9))
        ends += [snap(last + gap * i / m) for i in range(1, m)] + [k]
        last = k
    if len(ends) > 1 and ends[-1] - ends[-2] < 0.5 * d:  # (a sliver at the end joins the one before)
        del ends[-2]
    return np.array(ends)


def cut(
    motion: Motion,
    rate_hz: float,
    gain: np.ndarray,
    loop: LoopModel | None = None,
    v0: np.ndarray | None = None,
    tick0: int = 0,
    held0: np.ndarray | None = None,
) -> Sections:
    """Sections of 1/rate_hz s (the last shorter) covering the motion; gain = c2 / c1 per joint.
    With a loop model and sections long enough for it, the target velocities are fitted to it
    (cell.controller.loop); v0: the velocity the robot starts with, held0 the command it keeps
    (default v0), tick0 its status period in its command window."""
    d = 1.0 / rate_hz
    if motion.knots is not None and motion.duration > 1e-9:
        t_end = _knotted(motion.knots, motion.duration, d, loop.status_s if loop is not None else 0.0)
    else:
        n = max(1, math.ceil(motion.duration / d - 1e-9))
        # a motion of no length (already there) is one section of holding
        uniform = np.minimum(np.arange(1, n + 1) * d, motion.duration)
        if n > 1 and motion.duration - uniform[-2] < 0.5 * d:
            # a sliver at the end joins the section before: a last TP a few ms after the one before
            # gets no command of its own to the robot (0.56 mrad off at the end of a switched motion)
            uniform = np.delete(uniform, -2)
        t_end = uniform if motion.duration > 1e-9 else np.array([d])
    t_start = np.concatenate([[0.0], t_end[:-1]])
    duration = t_end - t_start
    q_end, v_end = motion.sample(t_end)
    q_start, _ = motion.sample(t_start)
    q_mid, _ = motion.sample((t_start + t_end) / 2)
    mean = (q_end - q_start) / duration[:, None]
    v_ff = mean - np.asarray(gain)[None, : q_end.shape[1]] * (q_end - q_mid)
    # (the sections' usual length decides: a short last one is fitted too, as it always was)
    usual = d if motion.knots is None or duration.size == 1 else float(duration[:-1].min())
    trace = None
    if loop is not None and usual >= loop.min_section_s():
        start = np.zeros(q_end.shape[1]) if v0 is None else np.asarray(v0, np.float64)
        v_ff, trace = loop.fit(q_end, t_end, q_start[0], start, tick0, held0)
    p_trg = loop.tp_positions(q_end, v_ff) if loop is not None else None
    return Sections(t_end, duration, q_end, v_ff, v_end, trace, p_trg)
