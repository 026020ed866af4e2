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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cell.controller.loop import LoopModel, LoopTrace
from cell.controller.plan import PlanError
from cell.trajectory.motion import Motion

FIT_ROUNDS = 48  # fit, hold against the plan, split where off: at most this often


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
    lead_s: float = 0.0  # led TPs (Led): the robot is on q[k] this long after t_end[k]
    deviation_m: float = math.nan  # led TPs: the modelled tool's largest distance from the plan

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


class Led(Motion):
    """A motion its TPs lead by one command window: it stands for `lead_s`, then runs `inner`.

    The command answering a window's last status acts in the next window, so a TP's command moves
    the robot a window after the TP is in force.  Fitted as Led (fit_led), TP k is in force one
    window before the part of the plan it moves the robot along, and each TP holds the robot onto
    the plan through its own section, however short: sections down to one command window stay
    stable (fitted without the lead they need six windows and more).  Sampled on the segment's
    clock, it says where the robot is meant to be (the plan a window late)."""

    def __init__(self, inner: Motion, lead_s: float, check_from_s: float = 0.0, strict: bool = True) -> None:
        self.inner, self.lead_s = inner, lead_s
        self.duration, self.dof = inner.duration + lead_s, inner.dof
        self.check_from_s = check_from_s  # the inner motion's time the bound holds from (after an approach)
        # a plan the bound cannot hold is refused (a trajectory followed); else fitted as close as one
        # TP a window gets (the controller's own fine motions)
        self.strict = strict

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, np.float64)
        q, v = self.inner.sample(np.clip(t - self.lead_s, 0.0, self.inner.duration))
        return q, np.where((t < self.lead_s)[:, None], 0.0, v)


# the tool's sensitivity at plan positions q (rows): a function of joint deviations dq there (same
# rows) giving the tool's distance from the plan, (m,) m; made once a fit, used every round
ToolError = Callable[[np.ndarray], Callable[[np.ndarray], np.ndarray]]


def fit_led(
    motion: Led,
    loop: LoopModel,
    rate_hz: float,
    tool_error: ToolError,
    bound_m: float,
    v0: np.ndarray | None = None,
    tick0: int = 0,
    held0: np.ndarray | None = None,
) -> Sections:
    """Led TPs where the plan needs them: sections of whole command windows, first 1/rate_hz long,
    fitted to the loop (LoopModel.fit with the lead), the modelled robot held against the plan at
    every status period (LoopModel.path) and each section the tool strays more than bound_m in
    split in two, until none does.  A section of one window still off is past what the TPs can do
    (one command a window): PlanError with where and by how much.  Few TPs where the plan is
    straight or slow, one a window where it turns fast."""
    inner, dt, w = motion.inner, loop.status_s, loop.window
    dof = inner.dof
    periods = max(1, round(inner.duration / dt))
    step = max(1, round(1.0 / (rate_hz * w * dt))) * w  # the first cut, in periods
    bounds = np.unique(np.concatenate([np.arange(step, periods, step), [periods]])).astype(np.int64)
    q0 = motion.sample(np.array([0.0]))[0][0]
    v0 = np.zeros(dof) if v0 is None else np.asarray(v0, np.float64)
    held0 = v0.copy() if held0 is None else np.asarray(held0, np.float64)
    # the plan where the robot should be after each period (the segment's clock: a window late),
    # and the tool's sensitivity there, a window at a time
    t_path = (np.arange(periods + w) + 1) * dt
    plan = motion.sample(t_path)[0]
    checked = t_path - motion.lead_s >= motion.check_from_s - 1e-12
    error_at = tool_error(plan[checked])
    for _ in range(FIT_ROUNDS):
        t_end = bounds * dt
        t_end[-1] = inner.duration
        q_end, v_end = inner.sample(t_end)
        v_ff, trace = loop.fit(q_end, t_end, q0, v0, tick0, held0, lead=w)
        ns = np.diff(bounds, prepend=0)
        # the TPs' path, with the final hold's first window (where the last section's command acts)
        hold_ns = np.append(ns, w)
        p_trg = np.vstack([q_end, q_end[-1:]])
        v_trg = np.vstack([v_ff, np.zeros((1, dof))])
        path = loop.path(hold_ns, p_trg, v_trg, q0, v0, held0, tick0)
        err = np.zeros(len(path))
        err[checked] = error_at(path[checked] - plan[checked])
        # each period's deviation is the work of the TP in force a window earlier
        owner = np.searchsorted(bounds, np.arange(len(path)) + 1 - w, side="right")
        worst = np.zeros(len(bounds) + 1)
        np.maximum.at(worst, np.minimum(owner, len(bounds)), err)
        off = np.flatnonzero(worst[: len(bounds)] > bound_m)
        if off.size == 0:
            break
        starts = np.concatenate([[0], bounds[:-1]])
        # a section of one window still off: its neighbours' commands reach into it (the state they
        # leave), so they are split in its stead until they are of one window too
        wide = {k for k in off.tolist() if ns[k] > w}
        wide |= {
            j for k in off.tolist() if ns[k] <= w for j in (k - 1, k + 1) if 0 <= j < len(ns) and ns[j] > w
        }
        splits = [starts[k] + (ns[k] // w // 2) * w for k in sorted(wide)]
        if not splits and not motion.strict:
            break
        if not splits:
            k = int(off[0])
            raise PlanError(
                f"the plan turns too fast for one TP a command window at t = {t_end[k] - ns[k] * dt:.3f}-"
                f"{t_end[k]:.3f} s: the robot would stray {worst[k] * 1e3:.3f} mm from it "
                f"(follow_tolerance_mm {bound_m * 1e3:g})"
            )
        bounds = np.unique(np.concatenate([bounds, np.array(splits, np.int64)]))
    else:
        k = int(np.argmax(worst[: len(bounds)]))
        raise PlanError(
            f"the plan turns too fast for one TP a command window around t = {t_end[k]:.3f} s: the "
            f"robot would stray {worst[k] * 1e3:.3f} mm from it (follow_tolerance_mm {bound_m * 1e3:g})"
        )
    p_pos = loop.tp_positions(q_end, v_ff)
    return Sections(
        t_end, np.diff(t_end, prepend=0.0), q_end, v_ff, v_end, trace, p_pos, motion.lead_s, float(err.max())
    )
