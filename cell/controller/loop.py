"""A model of the closed loop a TP drives, for choosing the TPs' target velocities.

Within a section the data plane commands v = (1-c1) v + c1 v_trg + c2 (p_trg - p)
on every status packet; the robot keeps the latest command of each window (the
answer to the window's last status) and executes it from the window's end,
within its acceleration limit.  A TP has
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

import ctypes
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell.dataplane.approx import TransformTable
from cell.native import NativeUnavailable, build
from cell.robot.datagram import SCALE

_CANDIDATES = 48
_STEPS = 12  # regula falsi steps after the grid pass, at most (two or three are usual)
_TOL_RAD = 1e-7  # a fitted TP puts the modelled robot this close to the plan (about 0.1 um at the tool)


_LOOP_C = Path(__file__).with_name("loop.c")


@functools.cache
def _native() -> ctypes.CDLL | None:
    """loop.c built (once per process), or None where it cannot be: run() then uses numpy."""
    try:
        lib = build("loop-model", (_LOOP_C,))
    except (NativeUnavailable, OSError):
        return None
    p, i64 = ctypes.c_void_p, ctypes.c_int64
    d = ctypes.c_double
    lib.loop_run.argtypes = [i64, i64, p, p, p, i64, i64, i64, p, p, p, p, p, p, d]
    lib.loop_run.restype = None
    lib.loop_fit.argtypes = [i64, i64, p, p, p, p, p, i64, i64, p, p, p, p, d, i64, i64, d, p, p, p, p, i64]
    lib.loop_fit.restype = ctypes.c_int
    lib.loop_path.argtypes = [i64, i64, p, p, p, p, p, p, i64, i64, p, p, p, p, d, p]
    lib.loop_path.restype = None
    return lib


TRACKABLE = 0.4  # (see trackable_accel)


def trackable_accel(drive_a_max: np.ndarray, window_s: float, section_s: float) -> np.ndarray:
    """The planned acceleration the fitted TPs can keep a robot on, per joint.

    Each section's TP sets one command that holds, nearly constant, through the section, and the
    command kept at its end acts for the next section's first window: an accelerating robot ends
    each section below the plan's speed, and the next TP must make up for it with a steeper ramp.
    That recursion is stable only while (plan's acceleration / drive's) + (window / section) stays
    below about 1/2 (with more, the speed error grows from TP to TP until no command can put the
    robot on the plan: 4 mrad, 1.8 mm at the tool, at 2.5 of the drives' 5 rad/s^2 and 10 TP/s).
    The bound keeps a margin: TRACKABLE rather than 1/2."""
    return np.asarray(drive_a_max, np.float64) * max(0.05, TRACKABLE - window_s / section_s)


@functools.cache
def _table(c: float, n_bits: int) -> TransformTable:
    """The data plane's Transform table for x -> c x (built once: a LoopModel is made per motion)."""
    return TransformTable(c, n_bits)


@dataclass(frozen=True)
class LoopTrace:
    """The modelled robot at a fitted motion's start (row 0) and at each section's end (row k + 1):
    where the loop model says it is, how fast it goes and the command it keeps, and how many status
    periods from the motion's start that is.  A motion branching off at a TP, or a stop cutting in
    between two, starts from this state: the robot's real one, to within the model's accuracy,
    where a prediction from its last status is off by the sample-and-hold between TPs (mrad)."""

    q: np.ndarray  # (n + 1, dof)
    v: np.ndarray
    held: np.ndarray
    periods: np.ndarray  # (n + 1,) int

    @classmethod
    def empty(cls, sections: int, dof: int, periods: np.ndarray | None = None) -> LoopTrace:
        """A trace to fill (periods: given, or zeros to fill too)."""
        rows = sections + 1
        if periods is None:
            periods = np.zeros(rows, np.int64)
        return cls(np.empty((rows, dof)), np.empty((rows, dof)), np.empty((rows, dof)), periods)


@dataclass(frozen=True)
class LoopModel:
    c1: np.ndarray  # the data plane's constants, per joint
    c2: np.ndarray
    v_max: np.ndarray  # what the data plane lets through (LimitVelocity) and the drive runs
    a_max: np.ndarray  # the drive's acceleration limit
    status_s: float = 0.002  # one status packet per joint this often
    window: int = 4  # status packets per command window
    n_bits: int = 0  # the data plane's Transform tables keep this many significant bits (0: exact)

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
        """n status periods of the loop from (q, v, the latest command kept); arrays broadcast over
        leading axes (candidates).  Returns the state at the end.

        The robot keeps the command answering a window's last status (tick % w == w - 1) and
        executes it from the next period on, when the window ends: so the command is computed
        there alone, and acts one period later.  Between two changes the drive's goal is
        constant and its acceleration-limited velocity has a closed form,
        v_j = v + clip(goal - v, +-j a dt), whose trapezoid sum moves q: a few array operations
        per window instead of a dozen per status period.  A command computed in a section's
        last period takes effect at the start of the next run (the next section).
        """
        if (native := _native()) is not None:
            return self._run_native(native, q, v, held, tick, n, p_trg, v_trg)
        return self.run_numpy(q, v, held, tick, n, p_trg, v_trg)

    def _run_native(self, lib: ctypes.CDLL, q, v, held, tick: int, n: int, p_trg, v_trg):
        """run() in C (loop.c): the same arithmetic, joint by joint, candidate by candidate."""
        shape = np.broadcast_shapes(
            np.shape(q), np.shape(v), np.shape(held), np.shape(p_trg), np.shape(v_trg)
        )
        rows = int(np.prod(shape[:-1], dtype=np.int64))
        arrays = []
        for x in (q, v, held, p_trg, v_trg):  # C-ordered float64 copies, broadcast to the full shape
            a = np.empty(shape)
            a[...] = x
            arrays.append(a)
        qo, vo, ho, pt, vt = arrays
        lib.loop_run(
            rows, shape[-1], qo.ctypes.data, vo.ctypes.data, ho.ctypes.data, int(tick), int(n),
            int(self.window), *self._per_joint[1], pt.ctypes.data, vt.ctypes.data, float(self.status_s),
        )  # fmt: skip
        return qo, vo, ho

    @functools.cached_property
    def _per_joint(self) -> tuple[tuple[np.ndarray, ...], tuple[int, ...]]:
        """c1, c2, v_max and a_max * status_s as float64 arrays (loop.c's per-joint inputs), and their
        addresses (the arrays cached with them, so they live as long)."""
        arrays = tuple(
            np.ascontiguousarray(np.atleast_1d(np.asarray(x, np.float64)))
            for x in (self.c1, self.c2, self.v_max, np.asarray(self.a_max, np.float64) * self.status_s)
        )
        return arrays, tuple(a.ctypes.data for a in arrays)

    def run_numpy(
        self,
        q: np.ndarray,
        v: np.ndarray,
        held: np.ndarray,
        tick: int,
        n: int,
        p_trg: np.ndarray,
        v_trg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """run() in numpy: the reference (and the fallback where no C compiler works)."""
        w = self.window
        pull = self.c1 * v_trg + self.c2 * p_trg  # the command's part that is fixed in the section
        goal = np.minimum(np.maximum(held, -self.v_max), self.v_max)
        i = 0
        while i < n:
            kept = (tick + i) % w == w - 1
            if kept:  # this status's answer is kept; it acts from the next period
                held = (1.0 - self.c1) * v + pull - self.c2 * q
                m = 1
            else:  # periods until the window's last status
                m = min(n - i, w - 1 - (tick + i) % w)
            gap = goal - v
            bound = self._bounds[:m].reshape((m,) + (1,) * (gap.ndim - 1) + (-1,))
            ramp = np.minimum(np.maximum(gap, -bound), bound)  # v_j - v, j = 1..m
            # trapezoid over the m periods: m v + (v_1 - v) + ... + (v_(m-1) - v) + (v_m - v) / 2
            q = q + (m * v + ramp.sum(axis=0) - 0.5 * ramp[-1]) * self.status_s
            v = v + ramp[-1]
            if kept:
                goal = np.minimum(np.maximum(held, -self.v_max), self.v_max)
            i += m
        return q, v, np.broadcast_to(held, np.broadcast_shapes(np.shape(held), np.shape(q)))

    @functools.cached_property
    def _bounds(self) -> np.ndarray:
        """(window, dof): how far the drive's velocity can move in 1, 2, ... status periods."""
        return np.arange(1, self.window + 1)[:, None] * (self.a_max * self.status_s)[None, :]

    def tp_positions(self, q: np.ndarray, v_trg: np.ndarray) -> np.ndarray:
        """The positions to load into TPs of target velocities v_trg and plan positions q (rows), so
        that the data plane's command is the model's to within the rounding of the tables' inputs.

        TransformTrgVelocity gives c1 v_trg to n significant bits only: at 8 bits up to 1/512 of
        it (2 mrad/s at 1 rad/s, 0.2 mrad over a section, 0.15 mm at the tool).  The controller
        knows the tables, so it moves the TP's position by the error / c2: the P term, whose
        exact part (the "(c-1)x" trick) passes fine differences through, adds it back."""
        if self.n_bits <= 0:
            return q
        x = np.rint(np.asarray(v_trg, np.float64) * SCALE).astype(np.int64)
        got = np.stack([_table(float(c), self.n_bits)(x[:, j]) for j, c in enumerate(self.c1)], axis=1)
        short = self.c1 * x - got  # wire units of velocity the table leaves out
        gain = np.where(self.c2 > 0, self.c2, np.inf)
        return q + short / gain / SCALE

    def path(
        self,
        ns: np.ndarray,
        p_trg: np.ndarray,
        v_trg: np.ndarray,
        q0: np.ndarray,
        v0: np.ndarray,
        held0: np.ndarray,
        tick0: int = 0,
    ) -> np.ndarray:
        """The modelled robot's positions after every status period of sections of ns periods with
        these TPs, from (q0, v0, held0): (sum ns, dof).  What the data plane's own interpolation
        makes of the TPs, to hold against the plan (cell.controller.tps.fit_led)."""
        ns = np.ascontiguousarray(ns, np.int64)
        dof = q0.size
        out = np.empty((int(ns.sum()), dof))
        q, v, held = (np.array(x, np.float64, order="C") for x in (q0, v0, held0))
        pt = np.ascontiguousarray(p_trg, np.float64)
        vt = np.ascontiguousarray(v_trg, np.float64)
        if (lib := _native()) is not None:
            lib.loop_path(
                ns.size, dof, ns.ctypes.data, pt.ctypes.data, vt.ctypes.data, q.ctypes.data, v.ctypes.data,
                held.ctypes.data, int(tick0), int(self.window), *self._per_joint[1], float(self.status_s),
                out.ctypes.data,
            )  # fmt: skip
            return out
        row, tick = 0, tick0
        for k, n in enumerate(ns.tolist()):
            for _ in range(n):
                q, v, held = self.run_numpy(q, v, held, tick, 1, pt[k], vt[k])
                out[row] = q
                row, tick = row + 1, tick + 1
        return out

    @property
    def window_s(self) -> float:
        """One command window (s): what led TPs lead their motion by (cell.controller.tps.Led)."""
        return self.window * self.status_s

    def min_section_s(self) -> float:
        return 6 * self.window * self.status_s

    def fit(
        self,
        q_end: np.ndarray,
        t_end: np.ndarray,
        q0: np.ndarray,
        v0: np.ndarray,
        tick0: int = 0,
        held0: np.ndarray | None = None,
        lead: int = 0,
    ) -> tuple[np.ndarray, LoopTrace]:
        """v_trg for each section (rows of q_end, ending at t_end s) so that the modelled robot,
        starting at (q0, v0) and keeping the command held0 (default v0), is on q_end at each
        section's end; and the modelled states on the way (LoopTrace).  lead (status periods, one
        command window): the TPs lead the motion (cell.controller.tps.Led), and the robot is on
        q_end that much after each section's end, when the command of its last window has acted;
        the trace stays at the sections' ends.

        Per section: a grid of candidates brackets the crossing (the end position grows with
        v_trg), then regula falsi closes in on it: the loop is piecewise linear in v_trg (a
        limit starts or stops acting at the kinks), so it lands exactly within a few steps.
        """
        if (native := _native()) is not None and q0.size <= 64:
            return self._fit_native(native, q_end, t_end, q0, v0, tick0, held0, lead)
        return self.fit_numpy(q_end, t_end, q0, v0, tick0, held0, lead)

    def _fit_native(
        self,
        lib: ctypes.CDLL,
        q_end: np.ndarray,
        t_end: np.ndarray,
        q0: np.ndarray,
        v0: np.ndarray,
        tick0: int,
        held0: np.ndarray | None,
        lead: int = 0,
    ) -> tuple[np.ndarray, LoopTrace]:
        """fit() in C (loop.c's loop_fit): the same steps, a whole motion in one call."""
        dof, sections = q0.size, len(t_end)
        q = np.array(q0, np.float64, order="C")
        v = np.array(v0, np.float64, order="C")
        held = v.copy() if held0 is None else np.array(held0, np.float64, order="C")
        targets = np.ascontiguousarray(q_end, np.float64).reshape(sections, dof)
        steps = np.diff(np.asarray(t_end, np.float64), prepend=0.0) / self.status_s
        ns = np.maximum(1, np.rint(steps)).astype(np.int64)  # (round half to even, as round())
        out = np.empty((sections, dof))
        trace = LoopTrace.empty(sections, dof, np.concatenate([[0], np.cumsum(ns)]).astype(np.int64))
        ok = lib.loop_fit(
            sections, dof, targets.ctypes.data, ns.ctypes.data, q.ctypes.data, v.ctypes.data,
            held.ctypes.data, int(tick0), int(self.window), *self._per_joint[1], float(self.status_s),
            _CANDIDATES, _STEPS, _TOL_RAD, out.ctypes.data, trace.q.ctypes.data, trace.v.ctypes.data,
            trace.held.ctypes.data, int(lead),
        )  # fmt: skip
        if ok != 0:
            return self.fit_numpy(q_end, t_end, q0, v0, tick0, held0, lead)
        return out, trace

    def fit_numpy(
        self,
        q_end: np.ndarray,
        t_end: np.ndarray,
        q0: np.ndarray,
        v0: np.ndarray,
        tick0: int = 0,
        held0: np.ndarray | None = None,
        lead: int = 0,
    ) -> tuple[np.ndarray, LoopTrace]:
        """fit() step by step in Python around run(): the reference (and the fallback)."""
        dof = q0.size
        joint = np.arange(dof)
        q, v = q0.astype(np.float64), v0.astype(np.float64)
        held = v.copy() if held0 is None else np.asarray(held0, np.float64)
        tick, t0 = tick0, 0.0
        out = np.empty((len(t_end), dof))
        trace = LoopTrace.empty(len(t_end), dof)
        trace.q[0], trace.v[0], trace.held[0] = q, v, held
        span = 4.0 * self.v_max + 1.0
        for k in range(len(t_end)):
            section = max(1, round((t_end[k] - t0) / self.status_s))
            n = section + lead
            target = q_end[k]
            cand = np.linspace(-span, span, _CANDIDATES)  # (C, dof)
            qe = np.broadcast_to(self.run(q, v, held, tick, n, target, cand)[0], cand.shape)
            i = np.clip((qe < target).sum(axis=0), 1, _CANDIDATES - 1)  # per joint: the bracket
            lo, hi = cand[i - 1, joint], cand[i, joint]
            f_lo, f_hi = qe[i - 1, joint] - target, qe[i, joint] - target
            side = np.zeros(dof)
            for _ in range(_STEPS):
                # regula falsi (Illinois): exact once the bracket is inside one linear piece
                rise = f_hi - f_lo
                frac = np.divide(-f_lo, rise, out=np.full(dof, 0.5), where=rise > 0)
                guess = lo + np.clip(frac, 0.0, 1.0) * (hi - lo)
                state = self.run(q, v, held, tick, n, target, guess)
                f = state[0] - target
                # done where on the plan, or where v_trg cannot matter (no command takes effect
                # within a section shorter than a window's rest)
                if np.all((np.abs(f) <= _TOL_RAD) | (rise <= 0)):
                    break
                low = f < 0
                lo, f_lo = np.where(low, guess, lo), np.where(low, f, f_lo)
                hi, f_hi = np.where(low, hi, guess), np.where(low, f_hi, f)
                # the end kept twice in a row counts half as much (keeps the steps from stalling)
                f_hi = np.where(low & (side < 0), 0.5 * f_hi, f_hi)
                f_lo = np.where(~low & (side > 0), 0.5 * f_lo, f_lo)
                side = np.where(low, -1.0, 1.0)
            out[k] = guess
            q, v, held = self.run(q, v, held, tick, section, target, guess) if lead else state
            tick += section
            t0 = float(t_end[k])
            trace.q[k + 1], trace.v[k + 1], trace.held[k + 1] = q, v, held
            trace.periods[k + 1] = tick - tick0
        return out, trace
