"""Motions prepared in the tables before the event that starts or changes them.

The controller's usual way is to plan when asked; these load the work ahead,
so that when the moment comes only table entries change (one update, no
planning), as the paper's design intends:

- armed starts (Sec. 7.2): several robots' motions loaded, each robot held on
  a TP that steps onto itself once a command window; one update setting a
  TrajectorySwitcher entry on each hold starts them all at the same hold step;
- loops (TPStepper): a lap loaded once, its last TP linking back to its first;
  it runs lap after lap until a switch entry on the last TP leads it out to a
  hold, after N laps or when asked;
- alternates (Sec. 6.1, Fig. 7): for a running motion, branches to other goals
  planned from each of its TPs ahead (the plan's own state there: nothing to
  predict) and loaded; taking one is one switch entry at the next TP the
  update can reach in time.

Each returns, or its waiter gets, a MotionResult as the other motions do, and
the controller's bookkeeping (what is loaded, where the robot will hold) is
kept as for them, so stops, re-plans and the next motion work as usual.
"""

from __future__ import annotations

import asyncio
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from cell.controller.motion import (
    Alternate,
    Armed,
    LoopRun,
    MotionResult,
    MotionStopped,
    Segment,
    Switch,
)
from cell.controller.plan import PlanError, plan_joint, plan_loop
from cell.controller.schedule import (
    SWITCH_MARGIN_NS,
    concat,
    hold_batch,
    modelled_at,
    tp_batch,
    window_ns,
)

if TYPE_CHECKING:  # (the facade whose parts these work on; it imports this module)
    from cell.controller.controller import Controller


def _window_ns(ctl: Controller, robot: int) -> int:
    return window_ns(ctl.book.grids.get(robot))


# --- armed starts ---------------------------------------------------------------------------------


def _first_after(ctl: Controller, robot: int, near: tuple[int, int] | None) -> tuple[int, int] | None:
    """beside()'s nearest status turned into the first status after a hold's step time (a quarter
    period before the lead's status): the one a robot on a grid of its own leaves its hold at."""
    grid = ctl.book.grids.get(robot)
    if near is None or grid is None:
        return near
    off, phase = near
    period, w = grid[1], grid[2]
    return (off + period, (phase + 1) % w) if off <= -period // 4 else (off, phase)


async def arm(ctl: Controller, goals: dict[int | str, np.ndarray], speed: float = 1.0) -> Armed:
    """Load each robot's joint motion to its goal behind a hold that steps onto itself once a
    command window (all holds at the same times, on the first robot's window grid).  A robot on a
    grid of its own leaves its hold at its first status after those times: its TPs are fitted for
    its window phase there."""

    tracks = [ctl.track(robot) for robot in goals]
    near = {
        r: _first_after(ctl, r, n)
        for r, n in (await ctl.engine.beside_lead([t.robot for t in tracks])).items()
    }
    planned = []
    for track, q_goal in zip(tracks, goals.values(), strict=True):
        await ctl.engine.confirm_running(track)
        q0 = await ctl.engine.start_q(track)
        motion = plan_joint(q0, np.asarray(q_goal, np.float64), track.limits.scaled(speed))
        beside = near[track.robot]
        phase = beside[1] if beside is not None else 0
        sections = await ctl.book.aside(partial(ctl.book.cut, track, motion, ctl.engine.rate_hz, tick0=phase))
        planned.append((track, motion, sections, track.take_ids(len(sections) + 2)))
    lead = planned[0][0].robot
    await ctl.engine.tables_in_hand()
    await ctl.link.state([t.robot for t in tracks])
    start, at, tick0 = ctl.book.grid_start(lead, ctl.link.now() + ctl.engine.lead_ns + 2 * ctl.link.rtt_ns)
    period = _window_ns(ctl, lead)
    batches, registers, remove, out = [], [], [], []
    for track, motion, sections, (hold_id, *ids) in planned:
        q0 = motion.sample(np.array([0.0]))[0][0]
        beside = near[track.robot]
        off, seg_tick0 = beside if beside is not None and tick0 is not None else (0, None)
        seg = Segment(start + off, motion, sections, ids, seg_tick0, track.robot)
        batches.append(hold_batch(track, hold_id, hold_id, q0, period / 1e9))
        batches.append(tp_batch(track, seg, 0, min(ctl.engine.episode, len(ids))))
        registers.append((track.robot, hold_id, at))
        remove += [(track.robot, i) for i in track.loaded]
        out.append((track, seg, hold_id))
    async with ctl.loading:
        await ctl.dp.update(insert=concat(batches), remove=remove, registers=registers)
        for track, seg, hold_id in out:
            track.loads += 1
            track.loaded = [hold_id, *seg.ids[: ctl.engine.episode]]
            track.segment, track.q_hold = None, seg.motion.sample(np.array([0.0]))[0][0]  # held there
    return Armed(out, period, at)


async def fire(ctl: Controller, armed: Armed, wait: bool = True) -> MotionResult:
    """Start armed motions: one update sets every hold's switch entry and moves every hold's next
    step to the same step of the lead's hold grid, the cell's lead (lead_s) ahead, as any start.
    Wherever in a window the update lands, every robot leaves at that step (one on a grid of its own
    at its first status after it, as armed), not one a window before another.  An update that lands
    after that step is counted late (late_starts): the robots then leave at their next statuses."""

    window = armed.period_ns
    earliest = ctl.link.now() + ctl.engine.lead_ns + 2 * ctl.link.rtt_ns
    k = max(0, -(-(earliest - armed.at_ns) // window))
    at = armed.at_ns + k * window
    switches = [(track.robot, hold_id, seg.ids[0]) for track, seg, hold_id in armed.planned]
    registers = [(track.robot, hold_id, at) for track, _, hold_id in armed.planned]
    async with ctl.loading:
        reply = await ctl.dp.update(switches=switches, registers=registers)
    starts = [seg.start_ns + k * window for _, seg, _ in armed.planned]
    if reply.now_ns > at:
        ctl.engine.late_starts += 1
        starts = [max(s, reply.now_ns) for s in starts]
    start = min(starts)
    for (track, seg, _), own in zip(armed.planned, starts, strict=True):
        seg.start_ns = own
        track.stop_reason = None
        track.segment, track.q_hold = seg, None
        ctl.engine.stream(track, seg)
        ctl.stopping.publish_plan(track, seg)
    tracks = [t for t, _, _ in armed.planned]
    end = max(seg.end_ns for _, seg, _ in armed.planned)
    q_end = np.concatenate([seg.sections.q[-1] for _, seg, _ in armed.planned])
    result = MotionResult(start, end, q_end)
    ctl.engine.last_fire = {t.robot: s for t, s in zip(tracks, starts, strict=True)}
    return await ctl.engine.finish(tracks, result) if wait else result


# --- loops ------------------------------------------------------------------------------------------


async def run_loop(
    ctl: Controller, robot: int | str, waypoints: list[np.ndarray], speed: float = 1.0, laps: int = 0
) -> LoopRun:
    """Load a lap (from where the robot stands through the waypoints and back) once, linked into a
    loop, and start it; it runs `laps` laps (0: until end_loop()).  Await run.done for the laps run."""

    if laps < 0:
        raise PlanError(f"laps must be >= 0 (0: until ended), got {laps}")
    track = ctl.track(robot)
    async with track.starting:
        await ctl.engine.confirm_running(track)
        q0 = await ctl.engine.start_q(track)
        await ctl.book.know_grid(track.robot)
        window = _window_ns(ctl, track.robot)
        motion = plan_loop(q0, waypoints, track.limits.scaled(speed), window / 1e9)
        sections = await ctl.book.aside(partial(ctl.book.cut, track, motion, ctl.engine.rate_hz, tick0=0))
        hold_id, *ids = track.take_ids(len(sections) + 2)  # the lap's TPs, then the exit hold
        await ctl.engine.tables_in_hand()
        await ctl.link.state()
        start, at, tick0 = ctl.book.grid_start(
            track.robot, ctl.link.now() + ctl.engine.lead_ns + 2 * ctl.link.rtt_ns
        )
        seg = Segment(start, motion, sections, ids, tick0, track.robot)
        lap = tp_batch(track, seg, 0, len(ids))  # the lap, then the exit hold
        lap.next_id[-2] = ids[0]  # TPStepper: the lap's last TP leads back to its first
        batches = [hold_batch(track, hold_id, ids[0], q0), lap]
        switches = [(track.robot, ids[-2], ids[-1])] if laps == 1 else []
        async with ctl.loading:
            reply = await ctl.dp.update(
                insert=concat(batches),
                remove=[(track.robot, i) for i in track.loaded],
                switches=switches,
                registers=[(track.robot, hold_id, at)],
            )
            track.loads += 1
            track.loaded = [hold_id, *ids]
        if reply.now_ns > start:
            ctl.engine.late_starts += 1
        track.stop_reason = None
        track.segment, track.q_hold = None, None
        run = LoopRun(track, q0, start, round(motion.duration * 1e9), ids[-2], ids[-1], laps)
        if laps == 1:
            run.done.set_result(1)
        ctl.engine.run_motion(track, _follow_loop(ctl, run))
        ctl.engine.loops[track.robot] = run
    return run


async def _follow_loop(ctl: Controller, run: LoopRun) -> None:
    """Set the exit when the laps asked for are nearly run; done once the robot holds at the start."""

    track = run.track
    try:
        if run.laps > 1:
            # during the last lap: after the lap before it has passed its last TP, well before this one's
            await ctl.link.sleep_until(run.lap_end_ns(run.laps - 1) + 50_000_000)
            await end_loop(ctl, track.robot)
        laps = await asyncio.shield(run.done)
        await ctl.link.sleep_until(run.lap_end_ns(laps) + 20_000_000)
        track.q_hold = run.q0
    finally:
        ctl.engine.loops.pop(track.robot, None)
        if not run.done.done():  # stopped (or lost) under way: whoever waits on the laps hears so
            run.done.set_exception(MotionStopped(track.stop_reason or "the loop was stopped"))
            run.done.exception()  # (retrieved: no warning if nobody waits)


async def end_loop(ctl: Controller, robot: int | str) -> int:
    """Lead the loop out at the end of the lap the update can still reach; how many laps it runs."""
    track = ctl.track(robot)
    run = ctl.engine.loops.get(track.robot)
    if run is None:
        raise PlanError(f"robot {robot} runs no loop")
    if run.done.done():
        return run.done.result()
    async with ctl.loading:
        reply = await ctl.dp.update(switches=[(track.robot, run.last_id, run.exit_id)])
    # it leads out at the first lap end after the entry was in (the reply's time is after that)
    laps = max(1, -(-(reply.now_ns - run.start_ns) // run.lap_ns))
    if reply.now_ns > run.lap_end_ns(laps) - 2 * _window_ns(ctl, track.robot):  # too close to call
        await ctl.link.sleep_until(run.lap_end_ns(laps) + 20_000_000)
        st = await ctl.link.state(track.robots)
        on = {r.robot_id: r.tp_id for r in st.robots}.get(track.robot)
        if on != run.exit_id:
            laps += 1
    run.done.set_result(laps)
    return laps


# --- alternates -----------------------------------------------------------------------------------


async def prepare_alternates(
    ctl: Controller, robot: int | str, goals: dict[str, np.ndarray], speed: float = 1.0, every: int = 1
) -> int:
    """For the robot's running motion: a branch to each goal from every `every`-th TP ahead (the
    first episode of each loaded now); how many TPs that loaded.

    Each branch is planned and its TPs fitted like any motion (about 5 ms a TP here): a 4 s motion
    at 10 TP/s with two alternates from every TP is some 80 branches, seconds of work, which is
    why they are prepared ahead; `every` trades that, and the TPs loaded, against how soon after
    the event the switch can come."""

    track = ctl.track(robot)
    seg = track.segment
    if not track.moving or seg is None:
        raise PlanError(f"robot {robot} is not moving: alternates branch off a running motion")
    ahead = ctl.link.now() + ctl.link.rtt_ns + 20_000_000
    ks = [k for k in range(0, len(seg.sections) - 1, max(1, every)) if seg.t_ns(k) >= ahead]
    prepared: dict[str, list[Alternate]] = {}
    batches = []
    loop = ctl.book.loop(track)
    for name, q_goal in goals.items():
        branches = []
        for k in ks:
            # from the loop model's robot at the TP where it has one (what a switch starts from), else
            # the plan there
            here = modelled_at(seg, loop, seg.t_ns(k))
            if here is None:
                q_k, v_k = seg.motion.sample(np.array([float(seg.sections.t_end[k])]))
                here = (q_k[0], v_k[0], v_k[0])
            q_k, v_k, held = here
            motion = plan_joint(q_k, np.asarray(q_goal, np.float64), track.limits.scaled(speed), v0=v_k)
            tick0 = ctl.book.phase_at(seg, seg.t_ns(k))
            sections = await ctl.book.aside(
                partial(ctl.book.cut, track, motion, ctl.engine.rate_hz, v_k, tick0, held)
            )
            ids = track.take_ids(len(sections) + 1)
            alt = Segment(
                seg.t_ns(k), motion, sections, ids, tick0 if seg.tick0 is not None else None, seg.robot
            )
            batches.append(tp_batch(track, alt, 0, min(ctl.engine.episode, len(ids))))
            branches.append(Alternate(k, alt))
        prepared[name] = branches
    if not batches:
        raise PlanError("the motion ends too soon to branch off it")
    batch = concat(batches)
    await ctl.engine.apply(track, batch, [])
    ctl.engine.alternates[track.robot] = (seg, prepared)
    return len(batch)


async def take_alternate(ctl: Controller, robot: int | str, name: str) -> MotionResult:
    """Switch onto the prepared branch `name` at the next TP the update reaches in time; returns
    when the branch has ended."""

    track = ctl.track(robot)
    main, prepared = ctl.engine.alternates.get(track.robot, (None, {}))
    if name not in prepared:
        raise PlanError(
            f"robot {robot} has no alternate {name!r} prepared (has {sorted(prepared) or 'none'})"
        )
    if track.segment is not main or not track.moving:
        raise PlanError(f"the motion alternate {name!r} was prepared for has ended")
    assert main is not None  # (it has alternates prepared)
    ahead = ctl.link.now() + ctl.link.rtt_ns + SWITCH_MARGIN_NS
    # the earliest branch point in reach whose TP of the main motion is loaded (streaming loads the
    # main motion an episode ahead: later branch points are not in the tables yet)
    alt = next((a for a in prepared[name] if main.t_ns(a.k) >= ahead and main.ids[a.k] in track.loaded), None)
    if alt is None:
        raise PlanError(
            f"too late to take alternate {name!r}: the motion's prepared branch points have passed"
        )
    branch = main.ids[alt.k]
    reply = await ctl.engine.apply(track, None, [], [(track.robot, branch, alt.segment.ids[0])])
    t_b = main.t_ns(alt.k)
    if reply.now_ns >= t_b - SWITCH_MARGIN_NS // 2:  # in place late: the data plane says which way
        await ctl.link.sleep_until(t_b + SWITCH_MARGIN_NS // 2)
        st = await ctl.link.state(track.robots)
        if not any(r.tp_id in alt.segment.ids for r in st.robots if r.robot_id == track.robot):
            await ctl.engine.apply(track, None, [], [(track.robot, branch, None)])
            raise PlanError(f"alternate {name!r} could not be switched in time")
    await ctl.stopping.halt(track)
    q_pred, v_pred = alt.segment.motion.sample(np.array([0.0]))
    ctl.engine.last_switch = Switch(branch, t_b, (t_b - reply.now_ns) / 1e6, q_pred[0], v_pred[0])
    ctl.engine.alternates.pop(track.robot, None)
    track.segment = alt.segment
    ctl.engine.stream(track, alt.segment)
    ctl.stopping.publish_plan(track, alt.segment)
    return await ctl.engine.finish(
        [track], MotionResult(t_b, alt.segment.end_ns, alt.segment.sections.q[-1].copy())
    )
