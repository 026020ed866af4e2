"""The motion schedule, sans I/O: what goes into the tables and when, decided from plans, statuses and
the data-plane time alone (no bus, no sockets)."""

from __future__ import annotations

import numpy as np
import pytest

from cell.controller.motion import HOLD_S, Segment, Track
from cell.controller.plan import MotionLimits, plan_joint
from cell.controller.schedule import (
    STALE_STATUS_NS,
    beside,
    branch_point,
    concat,
    dropped,
    episode_update,
    episode_wake,
    grid_start,
    hold_batch,
    moved_on,
    predict_at,
    status_of,
    stop_limits,
    stop_plan,
    taken,
    tp_batch,
)
from cell.controller.tps import cut
from cell.v1 import dataplane_pb2

LIMITS = MotionLimits(v_max=np.full(6, 3.0), a_max=np.full(6, 5.0), j_max=np.full(6, 50.0))
Q0 = np.array([0.0, -1.5, 1.5, -1.5, -1.5, 0.0])
START = 10_000_000_000


def segment(track: Track, sections: int = 10) -> Segment:
    """A joint motion cut into `sections` TPs (and its final hold)."""
    motion = plan_joint(Q0, Q0 + 0.6, LIMITS)
    sections = cut(motion, (sections - 0.5) / motion.duration, np.ones(6))
    return Segment(START, motion, sections, track.take_ids(len(sections) + 1))


def test_tps_link_one_after_another_and_the_final_hold_onto_itself() -> None:
    track = Track(1, [1], LIMITS)
    seg = segment(track)
    b = tp_batch(track, seg, 0, len(seg.ids))
    assert b.next_id[:-1].tolist() == seg.ids[1:] and b.next_id[-1] == seg.ids[-1]
    assert b.duration_s[-1] == HOLD_S and np.allclose(b.duration_s[:-1], seg.sections.duration)
    assert np.allclose(b.positions[-1], seg.sections.q[-1]) and not b.velocities[-1].any()
    h = hold_batch(track, 99, seg.ids[0], Q0)
    assert (h.id[0], h.next_id[0], h.duration_s[0]) == (99, seg.ids[0], HOLD_S)
    both = concat([h, b])
    assert both.id.tolist() == [99, *seg.ids] and both.positions.shape == (len(seg.ids) + 1, 6)


def test_episodes_go_in_one_ahead_and_come_out_three_behind() -> None:
    track = Track(1, [1], LIMITS)
    seg = segment(track)  # 10 TPs + the final hold: 11 ids
    n, ids = 3, seg.ids
    assert len(ids) == 11
    loaded = [0, *ids[:3]]  # the start's hold (id 0 here) and episode 0
    assert episode_wake(seg, 1, n) == seg.start_ns
    assert episode_update(seg, 1, n, loaded, set()) == (3, 6, [])
    loaded += ids[3:6]
    assert episode_wake(seg, 2, n) == seg.t_ns(2)  # as the robot enters episode 1
    assert episode_update(seg, 2, n, loaded, set()) == (6, 9, [0])  # the hold goes, episode 0 stays
    loaded = [i for i in loaded if i != 0] + ids[6:9]
    lo, hi, out = episode_update(seg, 3, n, loaded, keep={ids[1]})
    assert (lo, hi) == (9, 11) and out == [ids[0], ids[2]]  # episode 0, but what `keep` holds
    assert episode_wake(seg, 4, n) is None  # all loaded


def test_a_start_is_on_the_robots_tick_grid_its_register_a_quarter_period_early() -> None:
    period, w, offset = 2_000_000, 4, 5_000
    origin_rt = 1_000_000_000
    earliest = 1_234_567_890
    start, at, phase = grid_start((origin_rt, period, w), earliest, offset)
    origin = origin_rt - offset
    assert (start - origin) % (period * w) == 0 and phase == 0
    assert at == start - period // 4 and at >= earliest - period // 4
    assert start - (period * w) < earliest + period // 4 <= start  # the first window that fits
    assert grid_start(None, earliest, offset) == (earliest, earliest, None)


@pytest.mark.parametrize("waited_ms", [0, 1, 8, 57, 3_400])
def test_a_start_whose_update_waited_is_moved_on_by_whole_windows(waited_ms: int) -> None:
    """A launch that waited behind others' updates (a fleet launching hundreds of motions) moves its
    start on the lead's grid, window phase kept (its TPs were fitted for it): in place before it, not
    seconds after it."""
    period, w, offset = 2_000_000, 4, 5_000
    window = period * w
    start, at, _ = grid_start((1_000_000_000, period, w), 1_234_567_890, offset)
    earliest = at + waited_ms * 1_000_000
    new_start, new_at = moved_on(start, at, earliest, window)
    assert new_start - new_at == start - at and (new_start - start) % window == 0
    assert earliest <= new_at < earliest + window  # the first window it can reach, no later
    assert (new_start == start) == (waited_ms == 0)  # moved only if its time had passed
    assert moved_on(start, at, at - 1, window) == (start, at)  # in time: unchanged


@pytest.mark.parametrize("shift", [0, 30_000, 999_999, 1_000_000, 1_000_001, 5_300_000, -7_100_000])
def test_a_robot_started_beside_the_lead_starts_on_its_own_nearest_status_fitted_for_its_phase(
    shift: int,
) -> None:
    """Two robots on grids of their own (two models' emulators): at every start of the lead (a window
    start of its grid) the other's nearest status is within half a period, at a window phase that
    beside() says before the start time is known."""
    period, w = 2_000_000, 4
    lead = (1_000_000_000, period, w)
    other = (1_000_000_000 + shift, period, w)
    off, phase = beside(lead, other)
    assert abs(off) <= period // 2
    for k in (3, 17, 1000):
        start = lead[0] + k * period * w
        t = start + off
        assert (t - other[0]) % period == 0  # one of the other's statuses
        assert ((t - other[0]) // period) % w == phase
    assert beside(lead, (other[0], period // 2, w)) is None  # other rates: no fixed phase
    assert beside(None, other) is None and beside(lead, None) is None
    assert beside(lead, lead) == (0, 0)
    assert beside(lead, (lead[0] + 150, period, w)) == (0, 0)  # (an announcement's clock jitter)


def test_a_replan_branches_ahead_from_the_predicted_state() -> None:
    track = Track(1, [1], LIMITS)
    seg = segment(track)
    k = branch_point(seg, seg.t_ns(3) - 1)
    assert k == 3
    assert branch_point(seg, seg.end_ns) is None  # too late: the motion finishes first
    t_b = seg.t_ns(k)
    status_ns = seg.t_ns(1)
    q_plan, v_plan = seg.motion.sample(np.array([(status_ns - START) / 1e9, (t_b - START) / 1e9]))
    q, v = predict_at(seg, q_plan[0], v_plan[0], status_ns, t_b)
    assert np.allclose(q, q_plan[1]) and np.allclose(v, v_plan[1])  # on plan: the plan
    dq, dv = 0.01, 0.02  # behind and slow: carried to the branch (Sec. 6.1)
    q, _ = predict_at(seg, q_plan[0] - dq, v_plan[0] - dv, status_ns, t_b)
    assert np.allclose(q, q_plan[1] - dq - dv * (t_b - status_ns) / 1e9)


def test_a_stop_of_a_robot_without_a_motion_plans_to_rest_from_its_status_and_a_stale_one_stands() -> None:
    from cell.controller.loop import LoopModel

    track = Track(1, [1], LIMITS)
    loop = LoopModel(np.full(6, 4.0), np.full(6, 1.0), np.full(6, 3.0), np.full(6, 5.0), 0.002, 4)
    lim = stop_limits(LIMITS, np.full(6, 5.0))
    assert np.allclose(lim.a_max, 4.75) and lim.j_max[0] == 1000.0
    v = np.array([0.5, -0.4, 0.3, 0.0, 0.0, 0.1])
    now = START
    seg = stop_plan(track, (Q0, v, now - 1_000_000), now, now + 2_000_000, lim, np.ones(6), loop).segment
    q_end, v_end = seg.motion.sample(np.array([seg.motion.duration]))
    assert np.allclose(v_end, 0) and seg.motion.duration == pytest.approx(0.5 / 4.75, rel=0.1)
    assert np.all(np.sign(q_end[0] - Q0)[v != 0] == np.sign(v[v != 0]))  # it brakes onward
    stale = stop_plan(track, (Q0, v, now - STALE_STATUS_NS - 1), now, now, lim, np.ones(6), loop).segment
    assert np.allclose(stale.motion.sample(np.array([stale.motion.duration]))[0], Q0)  # it stands


def test_a_drop_ends_the_motion_only_if_newer_than_what_it_carries() -> None:
    tracks = {1: Track(1, [1], LIMITS), 2: Track(2, [2], LIMITS)}
    tracks[2].loaded_ns = 500
    st = dataplane_pb2.DataplaneState(
        robots=[
            dataplane_pb2.RobotPlaneState(robot_id=1, dropped_ns=300, dropped_why="watchdog"),
            dataplane_pb2.RobotPlaneState(robot_id=2, dropped_ns=400, dropped_why="quiet"),
        ]
    )
    seen: dict[int, int] = {}
    hit = dropped(st, seen, tracks.__getitem__)
    assert [(t.robot, "watchdog" in why) for t, why in hit] == [(1, True)]  # robot 2's is old news
    assert seen == {1: 300, 2: 400}
    assert dropped(st, seen, tracks.__getitem__) == []  # said once


def test_a_robot_another_controller_took_ends_the_motion_once_and_its_own_take_over_is_no_news() -> None:
    tracks = {1: Track(1, [1], LIMITS), 2: Track(2, [2], LIMITS)}
    me, other = 7, 9

    def state(*owners: int) -> dataplane_pb2.DataplaneState:
        robots = [dataplane_pb2.RobotPlaneState(robot_id=r, controller=c) for r, c in enumerate(owners, 1)]
        return dataplane_pb2.DataplaneState(robots=robots)

    owners: dict[int, int] = {}
    assert taken(state(me, 0), owners, me, tracks.__getitem__) == []  # ours, and nobody's
    hit = taken(state(me, other), owners, me, tracks.__getitem__)
    assert [(t.robot, "another controller took it over" in why) for t, why in hit] == [(2, True)]
    assert taken(state(me, other), owners, me, tracks.__getitem__) == []  # said once
    assert taken(state(me, me), owners, me, tracks.__getitem__) == []  # taken back (our take-over)


def test_a_status_counts_only_when_every_robot_of_the_track_has_one() -> None:
    track = Track(1, [1, 2], MotionLimits(np.full(12, 3.0), np.full(12, 5.0), np.full(12, 50.0)))
    s1 = dataplane_pb2.RobotPlaneState(robot_id=1, status_ns=7, position=[1.0] * 6, velocity=[0.5] * 6)
    s2 = dataplane_pb2.RobotPlaneState(robot_id=2, status_ns=5, position=[2.0] * 6, velocity=[0.0] * 6)
    assert status_of(track, {1: s1}) is None
    q, v, t = status_of(track, {1: s1, 2: s2})
    assert q.tolist() == [1.0] * 6 + [2.0] * 6 and v[:6].tolist() == [0.5] * 6 and t == 5
