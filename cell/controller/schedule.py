"""The motion schedule, sans I/O: what the controller loads into the data plane's tables, and when.

Everything here is a pure function of the plans, the statuses seen and the data-plane time; the
engine (cell.controller.engine) sends what these decide and keeps the answers:

- a motion is cut into TP sections and loaded as a Segment in episodes of n TPs; when the robot
  enters episode k-1, episode k goes in and episode k-3 comes out (`episode_update`), so at most
  3n TPs per robot are loaded and the controller has a whole episode's time to deliver the next;
- a motion starts on its robot's tick grid (`grid_start`), so its first TP meets the command window
  the TPs were fitted for;
- a re-plan branches off at a TP far enough ahead (`branch_point`) from the loop model's state there
  where the robot follows it, else the paper's prediction (`predict_state`, `predict_at`, Sec. 6.1);
- a stop is a motion planned from the model's state at the next command window, bridged to by copies
  of the old TPs, or from the last status (`stop_plan`);
- a robot whose trajectory the data plane dropped has its motion end with the reason (`dropped`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cell.controller.loop import LoopModel, LoopTrace
from cell.controller.motion import HOLD_S, Segment, Track
from cell.controller.plan import MotionLimits, SampledMotion, plan_stop
from cell.controller.tps import Sections, cut
from cell.dataplane.tables import TPBatch
from cell.v1 import dataplane_pb2

STOP_JERK = 1000.0  # rad/s^3: a stop reaches full deceleration in a few ms
SWITCH_MARGIN_NS = 20_000_000  # a switch entry must be in place this long before its TP
TIDY_NS = 20_000_000  # after a motion's end, when its TPs are deleted
STOP_RATE_HZ = 20.0  # TPs of a stop: sections still long enough to fit them to the loop
STOP_MARGIN_NS = 1_000_000  # a stop's update is planned to arrive this much before its window's last status
STALE_STATUS_NS = 50_000_000  # a robot's status older than this: no command reached it, it stands
WINDOW_NS = 8_000_000  # a command window, for robots that have not told their grid

Grid = tuple[
    int, int, int
]  # a robot's tick grid: (window origin, cell clock ns; status period ns; periods a window)


def tp_batch(track: Track, seg: Segment, lo: int, hi: int) -> TPBatch:
    """TPs lo..hi-1 of a segment, each linking to the next; the final hold links to itself."""
    ids = seg.ids
    nxt = [ids[min(i + 1, len(ids) - 1)] for i in range(lo, hi)]
    n = hi - lo
    return TPBatch(
        np.full(n, track.robot, np.int64),
        np.array(ids[lo:hi], np.int64),
        np.array(nxt, np.int64),
        seg.d[lo:hi],
        np.full(n, track.joints, np.int64),
        seg.q[lo:hi],
        seg.v[lo:hi],
    )


def hold_batch(
    track: Track, hold_id: int, next_id: int, q: np.ndarray, duration_s: float = HOLD_S
) -> TPBatch:
    """A TP holding q until the registers' start time, then on to next_id (an armed start's hold
    steps onto itself once a window: duration_s)."""
    return TPBatch(
        np.array([track.robot], np.int64),
        np.array([hold_id], np.int64),
        np.array([next_id], np.int64),
        np.array([duration_s]),
        np.array([track.joints], np.int64),
        q[None, :],
        np.zeros((1, track.joints)),
    )


def concat(batches: Sequence[TPBatch]) -> TPBatch:
    """Batches of TPs as one (positions padded to the widest entity)."""
    width = max(b.positions.shape[1] for b in batches)

    def pad(a: np.ndarray) -> np.ndarray:
        return np.pad(a, ((0, 0), (0, width - a.shape[1])))

    return TPBatch(
        np.concatenate([b.robot for b in batches]),
        np.concatenate([b.id for b in batches]),
        np.concatenate([b.next_id for b in batches]),
        np.concatenate([b.duration_s for b in batches]),
        np.concatenate([b.joints for b in batches]),
        np.concatenate([pad(b.positions) for b in batches]),
        np.concatenate([pad(b.velocities) for b in batches]),
    )


def episode_wake(seg: Segment, k: int, n: int) -> int | None:
    """When episode k of a segment loaded in episodes of n TPs goes in (data-plane clock): as the robot
    enters episode k-1.  None: the segment is all loaded."""
    if k * n >= len(seg.ids):
        return None
    return seg.t_ns(max(0, (k - 1) * n - 1)) if k > 1 else seg.start_ns


def episode_update(
    seg: Segment, k: int, n: int, loaded: Sequence[int], keep: set[int]
) -> tuple[int, int, list[int]]:
    """Episode k's TPs (lo, hi: ids lo..hi-1 go in) and what comes out with them: once k >= 2,
    whatever is loaded but neither in the last two episodes nor in `keep` (episode k-3 and older)."""
    ids = seg.ids
    if k < 2:
        return k * n, min((k + 1) * n, len(ids)), []
    stay = set(ids[(k - 2) * n :]) | keep
    return k * n, min((k + 1) * n, len(ids)), [i for i in loaded if i not in stay]


def tidy_ns(seg: Segment, rtt_ns: int) -> int:
    """When a segment's TPs but its final hold are deleted: once the robot is surely on that hold (our
    view of the data-plane clock may be off by half a round trip)."""
    return seg.end_ns + rtt_ns + TIDY_NS


# --- time ---------------------------------------------------------------------------------------------


def grid_start(grid: Grid | None, earliest_ns: int, realtime_offset_ns: int) -> tuple[int, int, int | None]:
    """When to start a motion of a robot with this tick grid at or after earliest_ns (data-plane
    clock): (plan start, register time, the model's window phase there).

    The data plane steps a trajectory at the first status after the register's time, and the robot
    keeps the answer to its window's last status: a start between two statuses, or in another window
    phase than the TPs were fitted for, puts the robot up to a status period behind the plan and its
    commands up to a window off (about 1 mm at the tool in a brisk move).  So a motion starts on a
    status period that begins a command window, its register a quarter period earlier (the status
    comes a little after it is due), and the TPs are fitted for phase 0.  A robot not heard
    announcing (grid None) starts at earliest_ns.  realtime_offset_ns: the cell clock less the
    data plane's (the grid is on the cell clock).
    """
    if grid is None:
        return earliest_ns, earliest_ns, None
    origin_rt, period, w = grid
    origin = origin_rt - realtime_offset_ns
    window = period * w
    k = -(-(earliest_ns + period // 4 - origin) // window)  # the next window's start
    start = origin + k * window
    return start, start - period // 4, 0


def beside(lead: Grid | None, other: Grid | None) -> tuple[int, int] | None:
    """Where another robot of a shared start starts beside the lead, whose start is on a window start
    of its own grid (grid_start): the offset of the other's nearest status from it (ns, within half a
    status period) and the other's window phase there, for its TPs to be fitted for.  The same at every
    start of the lead, so known before the start time is.  None if a grid is unknown, or the two
    tick at different rates (a phase that changes from start to start)."""
    if lead is None or other is None:
        return None
    (o1, p1, w1), (o2, p2, w2) = lead, other
    if p1 != p2 or w1 % w2:
        return None
    d = (o2 - o1) % p1
    e = d if d <= p1 // 2 else d - p1
    if abs(e) < p1 // 100:  # one grid: each announcement's clock offset jitters by 100s of ns
        e = 0
    return e, round((o1 - o2 + e) / p1) % w2


def phase_at(grid: Grid | None, seg: Segment, t_ns: int) -> int:
    """The model's window phase at a time on a segment started on its robot's grid (else 0)."""
    if seg.tick0 is None or grid is None:
        return 0
    _, period, w = grid
    return (seg.tick0 + round((t_ns - seg.start_ns) / period)) % w


def window_ns(grid: Grid | None) -> int:
    return WINDOW_NS if grid is None else grid[1] * grid[2]


def moved_on(start: int, at: int, earliest: int, window: int) -> tuple[int, int]:
    """A start (and its register time) moved on by whole command windows until the register is at or
    after `earliest`: its window phase, which the TPs were fitted for, is kept.  (A launch that waited
    for the data plane behind others: without it, the motion would be in place after its start.)"""
    if at >= earliest:
        return start, at
    shift = -(-(earliest - at) // window) * window
    return start + shift, at + shift


# --- re-planning ------------------------------------------------------------------------------------


def branch_point(seg: Segment, ahead_ns: int) -> int | None:
    """The first TP of the segment that ends at or after ahead_ns and is not its last section (None:
    too late to branch: the motion is to finish first)."""
    ends = np.array([seg.t_ns(k) for k in range(len(seg.sections))])
    later = np.flatnonzero(ends >= ahead_ns)
    k = int(later[0]) if later.size else -1
    return None if k < 0 or k >= len(seg.sections) - 1 else k


def predict_at(
    seg: Segment, q_s: np.ndarray, v_s: np.ndarray, status_ns: int, t_b: int
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's prediction of the robot's state at t_b: the plan there, corrected by how far off
    the plan the robot was at its last status (Sec. 6.1)."""
    t_rel = (status_ns - seg.start_ns) / 1e9
    q_traj, v_traj = seg.motion.sample(np.array([t_rel, (t_b - seg.start_ns) / 1e9]))
    dt = (t_b - status_ns) / 1e9
    return q_traj[1] + (q_s - q_traj[0]) + (v_s - v_traj[0]) * dt, v_traj[1]


State = tuple[np.ndarray, np.ndarray, np.ndarray]  # a robot in the loop: (q, v, the command it keeps)

FOLLOW_RAD = 1e-3  # a status this close to the loop model's robot (plus a period's travel): it follows


def modelled_at(seg: Segment, loop: LoopModel, t_ns: int) -> State | None:
    """The loop model's robot on the segment at t_ns (to the status period), from the state its fit
    traced at the section's start; after the last TP, the final hold.  None if the TPs were not
    fitted (short sections: the fine mode)."""
    s, tr = seg.sections, seg.sections.trace
    if tr is None:
        return None
    n = round((t_ns - seg.start_ns) / (loop.status_s * 1e9))
    k = max(0, int(np.searchsorted(tr.periods, n, side="right")) - 1)
    q, v, held = tr.q[k], tr.v[k], tr.held[k]
    rest = n - int(tr.periods[k])
    if rest <= 0:
        return q, v, held
    p_trg, v_trg = (s.q[k], s.v_ff[k]) if k < len(s) else (s.q[-1], np.zeros_like(v))
    return loop.run(q, v, held, (seg.tick0 or 0) + int(tr.periods[k]), rest, p_trg, v_trg)


def predict_state(
    seg: Segment, loop: LoopModel, status: tuple[np.ndarray, np.ndarray, int], t_ns: int
) -> tuple[State, bool]:
    """The robot's state at t_ns on its running segment, and whether it came from the loop model.

    The loop model's robot, where the robot's last status agrees with it (it follows its TPs):
    exact at a TP and between TPs too, with the command the robot keeps.  The paper's prediction
    from the last status (predict_at) is off by the sample-and-hold between TPs: the robot is
    up to a few mrad off the plan's curve there, and that offset, carried to the branch TP where the
    robot is back on the plan, was a jump of 3.5 mrad into the new motion.  A robot that does not
    follow (held on an underrun, stopped by its watchdog) gets the paper's prediction."""
    q_s, v_s, status_ns = status
    at_status, then = modelled_at(seg, loop, status_ns), modelled_at(seg, loop, t_ns)
    if at_status is not None and then is not None:
        slack = FOLLOW_RAD + np.abs(at_status[1]) * loop.status_s
        if np.all(np.abs(q_s - at_status[0]) <= slack):
            return (then[0].copy(), then[1].copy(), then[2].copy()), True
    q, v = predict_at(seg, q_s, v_s, status_ns, t_ns)
    return (q, v, v.copy()), False


# --- stops and losses ---------------------------------------------------------------------------------


def stop_limits(limits: MotionLimits, a_max: np.ndarray) -> MotionLimits:
    """A stop brakes with the drives' full deceleration (a_max, per joint), reached at once (they
    limit no jerk)."""
    n = limits.v_max.size
    return replace(limits, a_max=np.resize(a_max, n) * 0.95, j_max=np.full(n, STOP_JERK))


@dataclass
class StopPlan:
    """A stop as loaded: its segment, the TPs to insert and the robot's register to set."""

    segment: Segment
    batch: TPBatch
    register: tuple[int, int, int]  # (robot, the TP its register points at, when it steps on)
    modelled: bool  # from the loop model's robot (else from the last status)


def stop_plan(
    track: Track,
    status: tuple[np.ndarray, np.ndarray, int],
    now_ns: int,
    apply_ns: int,
    limits: MotionLimits,
    gain: np.ndarray,
    loop: LoopModel,
) -> StopPlan:
    """A stop of the track, the update expected at the data plane at apply_ns.

    A robot following its segment brakes on a plan its TPs meet to within their accuracy, as at a
    switch.  The stop starts at a command window's start t_w, the first whose last status comes
    after apply_ns: the robot enters that window in the loop model's state and keeps, for that
    window, the command the old TPs gave it (so the stop's plan coasts that window, then brakes
    as hard as plan_stop may).  Until t_w the register points at copies of the old segment's TPs
    (a bridge) that step onto the stop at t_w: however early the update comes, the robot meets the
    commands the model had for it.  A stop planned from the last status and set at once (as
    before) missed by a window whenever the update came late in one: 1-3 mm at the stop's TPs.

    A robot not following its segment (held, stopped by its watchdog, a status older than
    STALE_STATUS_NS: no command reached it, it stands) is stopped from its last status at once."""
    q, v, status_ns = status
    seg = track.segment
    if seg is not None and seg.start_ns <= now_ns and now_ns - status_ns <= STALE_STATUS_NS:
        period = round(loop.status_s * 1e9)
        w = loop.window
        origin = seg.start_ns - (seg.tick0 or 0) * period  # a window's start on the segment's grid
        window = w * period
        t_w = origin + -(-(apply_ns - origin - (w - 1) * period) // window) * window
        (q0, v0, held), modelled = predict_state(seg, loop, status, t_w)
        if modelled:
            return _modelled_stop(track, seg, loop, t_w, (q0, v0, held), now_ns, limits)
    if now_ns - status_ns > STALE_STATUS_NS:
        v = np.zeros_like(v)
    q_pred = q + v * max(0.0, (apply_ns - status_ns) / 1e9)
    motion = plan_stop(q_pred, v, limits)
    sections = cut(motion, STOP_RATE_HZ, np.resize(gain, track.joints), loop, v)
    stop = Segment(apply_ns, motion, sections, track.take_ids(len(sections) + 1))
    return StopPlan(
        stop, tp_batch(track, stop, 0, len(stop.ids)), (track.robot, stop.ids[0], stop.t_ns(0)), False
    )


def _modelled_stop(
    track: Track,
    seg: Segment,
    loop: LoopModel,
    t_w: int,
    state: State,
    now_ns: int,
    limits: MotionLimits,
) -> StopPlan:
    """The stop as the loop runs it: one TP a command window, each giving the robot the command
    that brakes it along its path (every joint's velocity scaled down together, the slowest to
    stop at limits.a_max) from the window after the one it coasts through on the command it keeps.
    The plan is the loop model's robot under those commands, so the robot is on it at every TP to
    within the model's accuracy; a plan_stop curve fitted with the usual TPs could not be followed
    (a section's one number meets its end position, not its end velocity: the robot came out of
    the braking still moving and overshot its stop by 1-2 mrad)."""
    period = round(loop.status_s * 1e9)
    w, dt, window_s = loop.window, loop.status_s, loop.window * loop.status_s
    q, v, held = (np.array(x, np.float64) for x in state)
    qs, vs, helds, path = [q], [v], [held], [q]
    t_end, q_end, v_trg, v_end = [], [], [], []
    scale = None
    m = 0
    while scale is None or m < scale.size:
        for i in range(w):  # the drive in window m, on the command kept from window m - 1
            if i == w - 1:
                q_k, v_k = q, v  # the window's last status, whose answer the robot keeps
            # (one period of the model's drive on the kept command: tick 0 computes none, and one it
            # computed would act only from the next period)
            q, v, _ = loop.run(q, v, held, 0, 1, q, np.zeros_like(q))
            path.append(q)
        if scale is None:  # once coasted: every joint's velocity down together, to 0 in brake_s
            brake_s = float(np.max(np.abs(v) / np.maximum(limits.a_max, 1e-9)))
            windows = max(1, math.ceil(brake_s / window_s - 1e-9))
            scale = np.clip(1.0 - np.arange(1, windows + 2) * window_s / max(brake_s, 1e-12), 0.0, 1.0)
            v_coast = v
        held = scale[m] * v_coast
        # the TP: u = (1 - c1) v_k + c1 v_trg + c2 (p_trg - q_k), with p_trg the section's end position
        v_trg.append((held - (1.0 - loop.c1) * v_k - loop.c2 * (q - q_k)) / loop.c1)
        t_end.append((m + 1) * window_s)
        q_end.append(q)
        v_end.append(v)
        qs.append(q)
        vs.append(v)
        helds.append(held)
        m += 1
    n = len(t_end)
    trace = LoopTrace(np.array(qs), np.array(vs), np.array(helds), np.arange(n + 1) * w)
    q_end_a, v_trg_a = np.array(q_end), np.array(v_trg)
    sections = Sections(
        np.array(t_end),
        np.full(n, window_s),
        q_end_a,
        v_trg_a,
        np.array(v_end),
        trace,
        loop.tp_positions(q_end_a, v_trg_a),
    )
    motion = SampledMotion(np.arange(len(path)) * dt, np.array(path))
    known = 0 if seg.tick0 is not None else None
    stop = Segment(t_w, motion, sections, track.take_ids(n + 1), known, seg.robot)
    # the bridge: the old TPs from the one running now to the one the status before t_w meets
    s, n_sec = seg.sections, len(seg.sections)
    t_rel = (np.array([now_ns, t_w - period]) - seg.start_ns) / 1e9
    first, last = (min(int(x), n_sec) for x in np.searchsorted(s.t_end, t_rel - 1e-12, side="left"))
    first = min(first, last)
    copies = list(range(first, last + 1))
    ids = track.take_ids(len(copies))
    ends = [seg.t_ns(k) for k in copies[:-1]] + [t_w]
    starts = [seg.start_ns if first == 0 else seg.t_ns(first - 1), *ends[:-1]]
    bridge = TPBatch(
        np.full(len(copies), track.robot, np.int64),
        np.array(ids, np.int64),
        np.array([*ids[1:], stop.ids[0]], np.int64),
        (np.array(ends) - np.array(starts)) / 1e9,
        np.full(len(copies), track.joints, np.int64),
        seg.q[copies],
        seg.v[copies],
    )
    batch = concat([bridge, tp_batch(track, stop, 0, len(stop.ids))])
    return StopPlan(stop, batch, (track.robot, ids[0], ends[0] - period // 4), True)


DROPPED = {
    "stop": "it was stopped over the Responsive Link (an e-stop, a stop, or a node's beacon watchdog)",
    "watchdog": "it went past its watchdog without commands (protective stop): its trajectory was dropped",
    "quiet": "no status from it for over 0.5 s (the robot, its host or its link went silent, or the data "
    "plane hung): its trajectory was dropped",
    "underrun": "its next TPs did not come in time (the controller fell behind): its trajectory was dropped",
}


def dropped(st: dataplane_pb2.DataplaneState, seen: dict[int, int], track_of) -> list[tuple[Track, str]]:
    """The tracks whose trajectory the data plane dropped since `seen` (robot -> the dropped_ns last
    seen, updated here), each with why; a drop before a track's current TPs went in is old news."""
    out = []
    for r in st.robots:
        before = seen.get(r.robot_id, 0)
        seen[r.robot_id] = r.dropped_ns
        track = track_of(r.robot_id)
        if r.dropped_ns > before and r.dropped_ns >= track.loaded_ns:
            why = DROPPED.get(r.dropped_why, "the data plane dropped its trajectory")
            out.append((track, f"robot {r.robot_id} stopped: {why}"))
    return out


def taken(
    st: dataplane_pb2.DataplaneState, owners: dict[int, int], me: int, track_of
) -> list[tuple[Track, str]]:
    """The tracks with a robot another controller than `me` took over since `owners` (robot -> the
    controller last seen owning it, updated here), each with why."""
    out = []
    for r in st.robots:
        before, owners[r.robot_id] = owners.get(r.robot_id, 0), r.controller
        if r.controller not in (0, me, before):
            why = "another controller took it over (it flushed the robot's tables as it started)"
            out.append((track_of(r.robot_id), f"robot {r.robot_id} lost: {why}"))
    return out


def stands_at(q: np.ndarray, v: np.ndarray, goal: np.ndarray | None, tolerance: float) -> bool:
    """Whether joints q, moving at v, stand at goal: every joint within tolerance (rad) of it (goal
    None: anywhere) and still (within 10x that per second)."""
    near = goal is None or np.abs(q - goal).max() <= tolerance
    return bool(near and np.abs(v).max() <= 10 * tolerance)


def status_of(
    track: Track, by_id: dict[int, dataplane_pb2.RobotPlaneState]
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The track's robots' last status (positions, velocities, the oldest time); None without one."""
    if any(r not in by_id or by_id[r].status_ns == 0 for r in track.robots):
        return None
    q = np.concatenate([np.array(by_id[r].position) for r in track.robots])
    v = np.concatenate([np.array(by_id[r].velocity) for r in track.robots])
    return q, v, min(by_id[r].status_ns for r in track.robots)
