"""Where one motion hands over to another mid-way (a switch at a TP, a stop between two), against the
real Tables and Pipeline closing the loop on a drive stepped tick by tick (cell.bench.loopsim, the
kinematic arm: no sockets, no clocks, exact timing).  The robot must then be on the new plan at its
TPs as closely as on a motion started at rest: its start state comes from the loop model, not from
a status extrapolated between TPs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cell.bench.loopsim import PERIOD_NS, WINDOW, Loop
from cell.controller.loop import trackable_accel
from cell.controller.motion import Segment, Track
from cell.controller.plan import plan_joint
from cell.controller.schedule import (
    predict_at,
    predict_state,
    stop_limits,
    stop_plan,
    tp_batch,
)
from cell.controller.tps import cut

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
DELTA = np.array([1.0, -0.4, 0.3, 0.2, 0.0, 0.5])


class Cell:
    """One arm on the real pipeline, with the controller's bookkeeping of its motion."""

    def __init__(self) -> None:
        self.loop = Loop("dataplane", "kinematic")  # (the default 8-bit tables, compensated for)
        self.model = self.loop.loop
        self.gain = self.loop.c2 / self.loop.c1
        self.track = Track(1, [1], self.loop.limits, next_id=10_000)
        self.seen: list[tuple[int, np.ndarray]] = []

    def start(self, goal: np.ndarray) -> Segment:
        """A motion to goal from where the arm is, started on a window's first period (as launched)."""
        lp = self.loop
        motion = plan_joint(lp.sim.q[0].copy(), goal, lp.limits)
        k0 = -(-(lp.tick + 2 * WINDOW) // WINDOW) * WINDOW
        start = 1_000_000_000 + k0 * PERIOD_NS
        secs = cut(motion, lp.rate, self.gain, self.model, tick0=0)
        first = lp.next_id
        lp._load(motion, secs, start)  # (a hold, the TPs, the final hold)
        ids = list(range(first + 1, first + len(secs) + 2))
        seg = Segment(start, motion, secs, ids, 0, 1)
        self.track.segment = seg
        return seg

    def until(self, t_ns: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Tick until the data-plane clock reaches t_ns; the last status (q, v, its time)."""
        lp = self.loop
        status = (lp.sim.q[0].copy(), lp.sim.qd[0].copy(), lp.now())
        while lp.now() < t_ns:
            status = (lp.sim.q[0].copy(), lp.sim.qd[0].copy(), lp.now())
            lp._tick(None, 0)  # type: ignore[arg-type]
            self.seen.append((lp.now(), lp.sim.q[0].copy()))
        return status

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        t = np.array([x for x, _ in self.seen], np.float64)
        q = np.array([y for _, y in self.seen])
        return np.stack([np.interp(t_ns, t, q[:, j]) for j in range(6)], axis=1)

    def off_plan(self, seg: Segment) -> np.ndarray:
        """|q - plan| at each of the segment's TPs (rad, the worst joint), once they have passed."""
        t_tp = seg.start_ns + np.rint(seg.sections.t_end * 1e9)
        self.until(int(t_tp[-1]) + PERIOD_NS)
        return np.abs(self.at(t_tp) - seg.sections.q).max(axis=1)


def test_a_switch_starts_from_the_loop_models_robot_and_stays_on_the_new_plan() -> None:
    cell = Cell()
    seg = cell.start(Q0 + DELTA)
    k = 6  # branch at the end of section 6, mid-way and at speed
    t_b = seg.t_ns(k)
    status = cell.until(t_b - 30_000_000)
    (q_b, v_b, held), modelled = predict_state(seg, cell.model, status, t_b)
    assert modelled
    q_paper, _ = predict_at(seg, *status, t_b)
    goal = Q0 + np.array([0.2, 0.2, -0.2, 0.0, 0.1, 0.0])
    motion = plan_joint(q_b, goal, cell.loop.limits, v0=v_b)
    tick0 = round((t_b - seg.start_ns) / PERIOD_NS) % WINDOW
    secs = cut(motion, cell.loop.rate, cell.gain, cell.model, v_b, tick0, held)
    new = Segment(t_b, motion, secs, cell.track.take_ids(len(secs) + 1), tick0, 1)
    cell.loop.tables.insert(tp_batch(cell.track, new, 0, len(new.ids)))
    cell.loop.tables.set_switch(1, seg.ids[k], new.ids[0])
    cell.until(t_b + PERIOD_NS)
    q_real = cell.at(np.array([t_b]))[0]
    # the model's robot at the branch is the real one (to the transform tables' rounding); the paper's
    # prediction from a status between TPs is off by the sample-and-hold there
    assert np.abs(q_real - q_b).max() < 2e-6
    assert np.abs(q_real - q_paper).max() > 50 * np.abs(q_real - q_b).max()
    assert cell.off_plan(new).max() < 5e-5


@pytest.mark.parametrize("early", [False, True])
def test_a_stop_brakes_on_its_plan_however_early_its_update_comes(early: bool) -> None:
    cell = Cell()
    seg = cell.start(Q0 + DELTA)
    t_stop = seg.t_ns(5) + 37_000_000  # between two TPs, at speed
    status = cell.until(t_stop)
    now = status[2] + PERIOD_NS
    lim = stop_limits(cell.loop.limits, cell.loop.sim.drives.a_max[0])
    stop = stop_plan(cell.track, status, now, now + 3 * PERIOD_NS, lim, cell.gain, cell.model)
    assert stop.modelled
    new = stop.segment
    # it starts on a window's first period, whose last status comes after the update
    assert (new.start_ns - seg.start_ns) % (WINDOW * PERIOD_NS) == 0
    assert new.start_ns + (WINDOW - 1) * PERIOD_NS >= now + 3 * PERIOD_NS > new.start_ns - PERIOD_NS
    # the update goes in now (early), or just before the first window's last status
    cell.until(now if early else new.start_ns + (WINDOW - 2) * PERIOD_NS)
    cell.loop.tables.insert(stop.batch)
    cell.loop.tables.set_registers(*stop.register)
    errors = cell.off_plan(new)
    assert errors.max() < 2e-6
    end = new.sections.q[-1]
    assert np.allclose(new.sections.q_plan_v[-1], 0.0)  # at rest at its end, having braked onward
    moving = np.abs(status[1]) > 0.05
    assert np.all(np.sign(end - status[0])[moving] == np.sign(status[1])[moving])
    cell.until(cell.loop.now() + 300_000_000)
    assert np.abs(cell.loop.sim.q[0] - end).max() < 5e-5 and np.abs(cell.loop.sim.qd[0]).max() < 1e-4
    # braking takes what the drive's deceleration allows (95 % of it), after the window it coasts
    speed = np.abs(status[1]).max()
    brake_s = (new.sections.t_end[-1] - new.sections.duration[0]) - new.sections.duration[-1]
    assert brake_s == pytest.approx(speed / lim.a_max.min(), abs=2 * WINDOW * PERIOD_NS / 1e9)


def test_a_robot_off_its_plan_is_stopped_from_its_status() -> None:
    cell = Cell()
    seg = cell.start(Q0 + DELTA)
    q, v, t = cell.until(seg.t_ns(3))
    lim = stop_limits(cell.loop.limits, cell.loop.sim.drives.a_max[0])
    stop = stop_plan(cell.track, (q + 0.01, v, t), t, t + 2 * PERIOD_NS, lim, cell.gain, cell.model)
    assert not stop.modelled
    assert stop.register == (1, stop.segment.ids[0], stop.segment.t_ns(0))
    assert np.allclose(stop.segment.motion.sample(np.array([0.0]))[0][0], q + 0.01 + v * 2 * PERIOD_NS / 1e9)


def test_the_planned_acceleration_is_capped_where_the_tps_can_no_longer_hold_the_robot() -> None:
    """The fit meets every TP with the default acceleration; at half the drives' (as planned before),
    its speed error grows from TP to TP until no command can put the model's robot on the plan."""
    lp = Loop("dataplane", "kinematic")
    drive = lp.sim.drives.a_max[0]
    bound = trackable_accel(drive, WINDOW * PERIOD_NS / 1e9, 1.0 / lp.rate)
    assert np.allclose(bound, 0.32 * drive) and np.all(lp.limits.a_max <= bound + 1e-9)
    goal = Q0 + np.array([1.05, 0.26, -0.35, 0.0, 0.0, 0.0])  # the demo's move that found it

    def worst(a_max: np.ndarray) -> float:
        motion = plan_joint(Q0, goal, replace(lp.limits, a_max=a_max))
        secs = cut(motion, lp.rate, lp.c2 / lp.c1, lp.loop, tick0=0)
        assert secs.trace is not None
        return float(np.abs(secs.q - secs.trace.q[1:]).max())

    assert worst(bound) < 1e-6
    assert worst(0.5 * drive) > 1e-3


def test_tp_positions_make_up_for_the_transform_tables_rounding() -> None:
    """TransformTrgVelocity keeps 8 significant bits of c1 v_trg (up to 2 mrad/s off at 1 rad/s): the
    TPs' positions carry the difference / c2, which the P term's exact part adds back."""
    from cell.bench.loopsim import reference_motions

    def worst(compensate: bool) -> float:
        lp = Loop("dataplane", "kinematic")
        if not compensate:
            lp.loop = replace(lp.loop, n_bits=0)
        return max(float(lp.run(m).max()) for m in reference_motions(lp.limits, 2))

    fine, rounded = worst(True), worst(False)
    assert fine < 0.02 and rounded > 5 * fine  # mm at the tool, at the TPs
