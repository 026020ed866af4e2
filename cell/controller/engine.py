"""The controller's engine: drives the motion schedule (cell.controller.schedule) against the data plane.

It never commands a joint: it loads TPs, sets switcher entries and registers, and deletes what has
been driven.  It may sit far from the data plane (10-100 ms of latency and jitter); what the robots
see does not depend on that, because each motion is loaded ahead of time (see the schedule).

The engine owns its tasks in one TaskGroup opened with it (`async with`): each motion's streaming,
each table update (carried through even when its caller is cancelled by a stop: the engine always
knows what it has loaded) and the robots' announcements.  A streaming task that fails ends the
motion it carries at once: it is logged, its waiters get the error, and the next motion plans from
where the robot is measured to stand.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Coroutine
from functools import partial
from typing import Any

import numpy as np

from cell.bus import Bus, BusError, FaultCode, RemoteError
from cell.config import CellConfig
from cell.controller.link import Link
from cell.controller.motion import (
    Alternate,
    Goal,
    LoopRun,
    MotionResult,
    MotionStopped,
    NotAtGoal,
    Segment,
    Switch,
    Track,
)
from cell.controller.plan import PlanError
from cell.controller.robots import RobotBook
from cell.controller.schedule import (
    TIDY_NS,
    beside,
    concat,
    episode_update,
    episode_wake,
    hold_batch,
    moved_on,
    stands_at,
    status_of,
    tidy_ns,
    tp_batch,
    window_ns,
)
from cell.controller.stopping import Stopping
from cell.controller.tps import Led
from cell.dataplane.client import DataplaneClient
from cell.dataplane.tables import TPBatch
from cell.trajectory.motion import Motion
from cell.v1 import dataplane_pb2

log = logging.getLogger("cell.controller")
# a followed trajectory's episodes (led TPs, up to one a command window) last this long at least, so
# that a busy host holding the controller back for a few hundred ms does not starve the tables
EPISODE_MIN_S = 1.0
CONFIRM_S = 1.5  # how long a motion asked for waits on the data plane to confirm a stop the controller holds


class Engine:
    """Motions launched, streamed episode by episode, switched and settled, on the tracks of `book`,
    with `stopping` for what ends them; every update that sets registers holds `loading` (shared
    with the stopping).  One of the controller's parts (cell.controller.controller)."""

    def __init__(
        self,
        bus: Bus,
        config: CellConfig,
        dp: DataplaneClient,
        link: Link,
        book: RobotBook,
        stopping: Stopping,
        loading: asyncio.Lock,
    ) -> None:
        self.bus, self.config, self.dp, self.link = bus, config, dp, link
        self.book, self.stopping, self.loading = book, stopping, loading
        cc = config.controller
        self.rate_hz, self.fine_hz, self.episode = cc.tp_rate_hz, cc.fine_rate_hz, cc.episode
        self.lead_ns = int(cc.lead_s * 1e9)
        self.plan_ns = 100_000_000  # how long planning a re-plan takes (measured, pessimistic)
        self.late_starts = 0  # motions whose first TPs were in place only after their start time
        self.start_shifts = 0  # starts moved on by whole windows while their update waited its turn
        self.not_at_goal = 0  # motions that ended with the robot read elsewhere (answered failed)
        self.last_switch: Switch | None = None
        self.unfinished: dict[int, Goal] = {}  # robot -> the motion a stop interrupted (for resume)
        # set while supervise() has the tables in hand: motions wait for it (a take-over's flush
        # must not sweep away a motion loaded meanwhile); None: not supervised (tests, benches)
        self.tables_ready: asyncio.Event | None = None
        # robot -> its track's `loads` when its TPs were last lost: supervise() flushes them once it can,
        # unless a motion was loaded since (a flush decided before a load must never land after it)
        self.pending_flush: dict[int, int] = {}
        # motions prepared ahead (cell.controller.prepared): loops under way, alternates loaded for a
        # robot's running motion, and the start of each robot of the last armed start
        self.loops: dict[int, LoopRun] = {}
        self.alternates: dict[int, tuple[Segment, dict[str, list[Alternate]]]] = {}
        self.last_fire: dict[int, int] = {}
        self._group: asyncio.TaskGroup | None = None
        self._exit = contextlib.AsyncExitStack()
        self._announcements: asyncio.Task | None = None

    # --- lifecycle and tasks ------------------------------------------------------------------------

    async def __aenter__(self) -> Engine:
        self._group = await self._exit.enter_async_context(asyncio.TaskGroup())
        sub = await self.bus.subscribe("announce/robot/")
        self._announcements = self._group.create_task(
            self.book.follow_announcements(sub), name="announcements"
        )
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            await self.aclose()
        finally:
            self._group = None
            await self._exit.aclose()  # (waits for the updates still in flight)

    async def aclose(self) -> None:
        """Stop streaming (the robots hold where their loaded TPs take them) and wait for it."""
        if self._announcements is not None:
            self._announcements.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._announcements
            self._announcements = None
        for t in list(self.book.tracks.values()):
            await self.stopping.halt(t)

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task:
        if self._group is None:
            coro.close()
            raise RuntimeError("the controller runs its motions inside `async with Controller(...)`")
        return self._group.create_task(coro, name=name)

    def episode_of(self, seg: Segment) -> int:
        """TPs of the segment loaded at a time (episode_update)."""
        return seg.episode or self.episode

    def stream(self, track: Track, seg: Segment, next_episode: int = 1) -> None:
        """Stream the segment into the tables from episode next_episode on, in the task group."""
        self.run_motion(track, self._stream(track, seg, next_episode))

    def run_motion(self, track: Track, coro: Coroutine[Any, Any, None]) -> None:
        """A track's motion task: a failure ends the motion at once (said, and kept for its waiters),
        never the task group."""

        async def guarded() -> None:
            try:
                await coro
            except Exception as exc:
                track.failure = exc
                why = str(exc) if isinstance(exc, NotAtGoal) else f"its streaming failed: {exc}"
                track.stop_reason = track.stop_reason or why
                log.error("the motion of robot(s) %s failed: %s", track.robots, exc)

        track.failure = None
        track.task = self.spawn(guarded(), f"motion-{track.robot}")

    async def _held_why(self, track: Track) -> str:
        """What the data plane says of the track's robots (where a motion ended elsewhere: the TP each
        follows, a Responsive Link stop, a stall, a dropped trajectory), as a clause; "" unanswered."""
        try:
            st = await self.link.state(track.robots, timeout=0.5)
        except (BusError, TimeoutError):
            return ""
        said = []
        for r in st.robots:
            flags = [f for f, on in (("stopped", r.stopped), ("stalled", r.stalled)) if on]
            dropped = f", dropped ({r.dropped_why})" if r.dropped_ns else ""
            said.append(f"robot {r.robot_id} at TP {r.tp_id}{''.join(', ' + f for f in flags)}{dropped}")
        return f"; the data plane: {'; '.join(said)}" if said else ""

    async def joints_now(self, track: Track) -> tuple[np.ndarray, np.ndarray, int]:
        """The last status of the track's robots: positions, velocities, its data-plane time."""
        st = await self.link.state(track.robots)
        status = status_of(track, {r.robot_id: r for r in st.robots})
        if status is None:
            raise PlanError(f"no status from robot(s) {track.robots} at the data plane yet")
        return status

    def released(self, st: dataplane_pb2.DataplaneState, asked: float) -> None:
        """The data plane is the authority on Responsive Link stops (every stop reaches it first); the
        hub's events on the bus only tell sooner, or late: a robot held for stopped since before this
        reading (asked: its time.monotonic()), and that the data plane no longer holds, was released
        while its release went unheard or is still on its way (a hub's backlog, a controller that
        started between the stop and the release, a stop's check still waiting on the data plane)."""
        free = {r.robot_id for r in st.robots if not r.stopped}
        for robot in [r for r, since in self.book.stopped.items() if since < asked and r in free]:
            self.book.stopped.pop(robot, None)

    async def confirm_running(self, track: Track) -> None:
        """check_running, once the data plane has confirmed the stops the controller holds: a motion
        asked for right after a release must not be refused for news of the release still on its way.
        Unanswered, the stop holds."""
        if any(r in self.book.stopped for r in track.robots):
            asked = time.monotonic()
            with contextlib.suppress(BusError, TimeoutError):
                self.released(await self.link.state(track.robots, timeout=CONFIRM_S), asked)
        self.check_running(track)

    def check_running(self, track: Track) -> None:
        held = [r for r in track.robots if r in self.book.stopped]
        if held:
            raise MotionStopped(f"robot(s) {held} stopped over the Responsive Link: resume first")
        for r in track.robots:
            if r in self.book.programs:
                raise MotionStopped(
                    f"robot {r}: {self.book.programs[r]}; the cell drives it again once it ends"
                )

    # --- motions -----------------------------------------------------------------------------

    async def start_q(self, track: Track) -> np.ndarray:
        """Where the track's next motion starts: after the one under way (it waits for it)."""
        await self.wait_idle(track)
        if track.q_hold is not None:
            return track.q_hold
        return (await self.joints_now(track))[0]

    async def wait_idle(self, robot: int | str | Track) -> None:
        """Until the robot's motion under way has ended; MotionStopped if it was stopped."""
        track = robot if isinstance(robot, Track) else self.book.track(robot)
        task = track.task
        if task is None or task.done():  # (a task cancelled by an earlier stop: start from the stop)
            return
        try:
            await asyncio.shield(task)
        except asyncio.CancelledError:
            me = asyncio.current_task()
            if me is not None and me.cancelling():
                raise
            raise MotionStopped(track.stop_reason or "the motion under way was stopped") from None
        if not isinstance(track.failure, NotAtGoal):  # (that one is its own caller's: we start from
            _raise_failure(track.failure)  # where the robot stands)

    async def tables_in_hand(self) -> None:
        """Until supervise() has the data plane's tables in hand (its take-over at our start, or after
        a loss, clears them: a motion loaded before would be swept away)."""
        if self.tables_ready is not None and not self.tables_ready.is_set():
            try:
                async with asyncio.timeout(self.config.bus.request_timeout_s):
                    await self.tables_ready.wait()
            except TimeoutError:
                raise MotionStopped("the data plane is not answering: no motion can start") from None

    async def beside_lead(self, robots: list[int]) -> dict[int, tuple[int, int] | None]:
        """Robots started together: the first (the lead) starts on a window start of its grid; each
        other at its own status nearest to that, fitted for its window phase there (schedule.beside:
        the grids of two models' emulators differ).  None: a grid not known beside the lead's."""
        for robot in robots:
            await self.book.know_grid(robot)
        lead = self.book.grids.get(robots[0])
        return {r: (0, 0) if k == 0 else beside(lead, self.book.grids.get(r)) for k, r in enumerate(robots)}

    async def launch(
        self, motions: dict[int, Motion], fine: bool = False
    ) -> tuple[MotionResult, list[Track]]:
        """Load the motions' first episodes and start them at one data-plane time, in one atomic
        update; they stream on in the background."""
        rate = self.fine_hz if fine else self.rate_hz
        await self.tables_in_hand()
        # a stop, a program taking a robot over, a loss while this motion is planned and loaded bumps
        # its track's epoch: the motion must not then run (it would stream to a robot that is not ours)
        epochs = {r: self.book.track(r).epoch for r in motions}
        lead_id = next(iter(motions))
        near = await self.beside_lead(list(motions))
        planned = []
        for robot, motion in motions.items():
            track = self.book.track(robot)
            await self.confirm_running(track)
            # (in a worker thread: fitting a long motion's TPs takes 0.1-0.5 s of CPU, which would hold
            # up everything else this controller does, its watch on the data plane too)
            beside = near[robot]
            phase = beside[1] if beside is not None else 0
            if fine and not isinstance(motion, Led):  # (fine: led TPs fitted to the plan, as close as
                # one a command window gets, within follow_tolerance_mm)
                motion = Led(motion, self.book.loop(track).window_s, strict=False)
            sections = await self.book.aside(partial(self.book.cut, track, motion, rate, tick0=phase))
            planned.append((track, motion, sections, track.take_ids(len(sections) + 2)))
        # the start time is set once the planning is done, so that the lead only has to cover the
        # update's way to the data plane (planning first would eat it on a busy host: a late start)
        await self.link.state([t.robot for t, *_ in planned])  # a fresh clock and round trip (its robots')
        start, at, tick0 = self.book.grid_start(
            lead_id, self.link.now() + self.lead_ns + 2 * self.link.rtt_ns
        )
        for track, *_ in planned:
            self.check_running(track)
        try:
            async with self.loading:
                # (the lock may have been waited for: a fleet launching hundreds of motions queues
                # here, and a start set before the wait would be in place seconds late.  Moved on by
                # whole command windows, it keeps its window phase: the TPs fitted for it hold)
                start, at = self.still_ahead(lead_id, start, at)
                segments, update = self.first_episodes(planned, near, start, at, tick0)
                reply = await self.dp.update(**update)
                for track, _, _ in segments:
                    track.loads += 1
        except RemoteError as exc:
            if exc.code == FaultCode.STOPPED:  # stopped on the link before we heard of it
                raise MotionStopped(exc.message) from None
            raise
        except BusError as exc:  # it may yet be applied, late: it must not start unseen
            tracks = [t for t, *_ in planned]
            why = f"the data plane did not confirm the motion's start: {exc}"
            self.stopping.lose(tracks, why)
            self.pending_flush.update({r: t.loads for t in tracks for r in t.robots})
            raise MotionStopped(tracks[0].stop_reason or why) from None
        if moved_on := [t for t, _, _ in segments if t.epoch != epochs[t.robot]]:
            loaded = [
                (t.robot, i)
                for t, seg, hold_id in segments
                for i in (hold_id, *seg.ids[: self.episode_of(seg)])
            ]
            with contextlib.suppress(RemoteError, BusError):
                async with self.loading:
                    await self.dp.update(remove=loaded)
            why = moved_on[0].stop_reason or "the robot was stopped while its motion was loaded"
            raise MotionStopped(why)
        if reply.now_ns > start:  # in place after the start time: the robots catch up with the plan
            self.late_starts += 1
            log.warning(
                "motion of %s in place %.1f ms after its start time (lead %.0f ms, round trip %.1f ms)",
                ", ".join(str(t.robot) for t, _, _ in segments),
                (reply.now_ns - start) / 1e6,
                self.lead_ns / 1e6,
                self.link.rtt_ns / 1e6,
            )
        for track, seg, hold_id in segments:
            track.stop_reason = None
            track.loaded_ns = reply.now_ns
            track.loaded = [hold_id, *seg.ids[: self.episode_of(seg)]]
            track.segment = seg
            track.q_hold = None  # moving: where it ends is the segment's end
            self.stream(track, seg)
            self.stopping.publish_plan(track, seg)
        end = max(seg.end_ns for _, seg, _ in segments)
        q_end = np.concatenate([seg.sections.q[-1] for _, seg, _ in segments])
        return MotionResult(start, end, q_end), [t for t, _, _ in segments]

    def still_ahead(self, lead: int, start: int, at: int) -> tuple[int, int]:
        """(start, register time) as `launch` set them, or moved on if its update can no longer reach
        the data plane before them (schedule.moved_on, on the lead's grid)."""
        earliest = self.link.now() + 2 * self.link.rtt_ns + self.lead_ns // 4
        moved = moved_on(start, at, earliest, window_ns(self.book.grids.get(lead)))
        self.start_shifts += moved != (start, at)
        return moved

    def first_episodes(
        self, planned: list, near: dict, start: int, at: int, tick0: int | None
    ) -> tuple[list[tuple[Track, Segment, int]], dict]:
        """The launch's segments and its one atomic update: each robot's hold (its register set to
        `at`, beside the lead's), its first episode, the TPs it had loaded removed."""
        first: list[TPBatch] = []
        registers, remove, segments = [], [], []
        for track, motion, sections, (hold_id, *ids) in planned:
            q0 = motion.sample(np.array([0.0]))[0][0]
            # (a robot whose grid is not known beside the lead's: started with it, phase unknown to the fit)
            off, phase = (
                near[track.robot] if near[track.robot] is not None and tick0 is not None else (0, None)
            )
            # (an episode lasts EPISODE_MIN_S at least: dense TPs, a followed trajectory's, in
            # episodes of the usual count would leave the controller a fifth of a second to deliver each)
            per_s = len(sections) / max(float(sections.t_end[-1]), 1e-9) if sections.lead_s else 0.0
            n = max(self.episode, math.ceil(EPISODE_MIN_S * per_s))
            seg = Segment(start + off, motion, sections, ids, phase, track.robot, episode=n)
            first.append(hold_batch(track, hold_id, ids[0], q0))
            first.append(tp_batch(track, seg, 0, min(n, len(ids))))
            registers.append((track.robot, hold_id, at + off))
            remove += [(track.robot, i) for i in track.loaded]
            segments.append((track, seg, hold_id))
        return segments, {"insert": concat(first), "remove": remove, "registers": registers}

    async def finish(self, tracks: list[Track], result: MotionResult) -> MotionResult:
        """Until the tracks' motions have ended; MotionStopped if one was stopped or re-planned."""
        try:
            await asyncio.gather(*(t.task for t in tracks if t.task is not None))
        except asyncio.CancelledError:
            me = asyncio.current_task()
            if me is not None and me.cancelling():
                raise  # we are cancelled ourselves
            why = next((t.stop_reason for t in tracks if t.stop_reason), None)
            raise MotionStopped(why or "the motion was stopped or re-planned") from None
        _raise_failure(next((t.failure for t in tracks if t.failure is not None), None))
        for track in tracks:
            self.unfinished.pop(track.robot, None)
        return result

    async def _stream(self, track: Track, seg: Segment, next_episode: int) -> None:
        """Load episode after episode ahead of the robot; then tidy up behind it."""
        k = next_episode
        n = self.episode_of(seg)
        while (wake := episode_wake(seg, k, n)) is not None:
            await self.link.sleep_until(wake)
            lo, hi, old = episode_update(seg, k, n, track.loaded, self._prepared_ids(track, seg))
            await self.apply(track, tp_batch(track, seg, lo, hi), old)
            k += 1
        # all but the final hold go once the robot is on it (a deletion that comes too early is
        # refused as in_use; retry)
        await self.link.sleep_until(tidy_ns(seg, self.link.rtt_ns))
        old = [i for i in track.loaded if i != seg.ids[-1]]
        for attempt in range(20):
            try:
                if old:
                    await self.apply(track, None, old)
                break
            except RemoteError as exc:
                if exc.code != FaultCode.IN_USE or attempt == 19:
                    raise
                await asyncio.sleep(TIDY_NS / 1e9)
        track.q_hold = seg.sections.q[-1].copy()
        await self.settle(track, seg.end_ns)

    async def settle(self, track: Track, end_ns: int) -> None:
        """Until the track's robots are read standing at the end of its motion: a status measured
        after the plan's end (end_ns, data-plane clock) with every joint within the goal tolerance
        and still.  The one gate of a `done` (its motion task ends only then): a motion whose TPs
        all went in but whose robot is elsewhere raises NotAtGoal with where it stands, at most
        settle_s after the plan's end, and the next motion plans from where the robot stands."""
        cc = self.config.controller
        tol, goal = cc.goal_tolerance_rad, track.q_hold
        assert goal is not None
        deadline = max(end_ns, self.link.now()) + int(cc.settle_s * 1e9)
        await self.link.sleep_until(end_ns)  # (no status before the plan's end can say it arrived)
        while True:
            q, v, t_ns = await self.joints_now(track)
            if t_ns >= end_ns and stands_at(q, v, goal, tol):
                return
            if self.link.now() >= deadline:
                err = np.abs(q - goal)
                j = int(err.argmax())
                self.not_at_goal += 1
                track.q_hold = None  # (the next motion starts from where it stands)
                raise NotAtGoal(
                    f"robot(s) {track.robots} not at the goal {cc.settle_s:g} s after the motion's end: "
                    f"joint {j} stands {err[j]:.4f} rad from it (tolerance {tol:g}), moving at up to "
                    f"{np.abs(v).max():.4f} rad/s; joints {np.round(q, 4).tolist()}"
                    + ("" if t_ns >= end_ns else "; no status since the motion's end")
                    + await self._held_why(track)
                )
            await asyncio.sleep(0.005)

    def _prepared_ids(self, track: Track, seg: Segment) -> set[int]:
        """The TPs of alternates prepared for this segment: streaming leaves them loaded."""
        main, branches = self.alternates.get(track.robot, (None, {}))
        if main is not seg:
            return set()
        return {i for alts in branches.values() for a in alts for i in a.segment.ids[: self.episode]}

    async def apply(
        self,
        track: Track,
        insert: TPBatch | None,
        remove: list[int],
        switches: list[tuple[int, int, int | None]] | None = None,
    ) -> dataplane_pb2.UpdateReply:
        """One update of a track's TPs with its bookkeeping, carried through even if the caller is
        cancelled (a stop): the controller always knows what it has loaded."""
        generation = track.generation
        done: asyncio.Future[dataplane_pb2.UpdateReply] = asyncio.get_running_loop().create_future()

        async def go() -> None:
            try:
                reply = await self.dp.update(
                    insert=() if insert is None else insert,
                    remove=[(track.robot, i) for i in remove],
                    switches=switches or [],
                )
            except Exception as exc:  # (the caller's to raise, never the task group's)
                done.set_exception(exc)
                done.add_done_callback(lambda f: f.exception())  # (retrieved if its caller is gone)
                return
            if track.generation == generation:  # (else the tables it went into are gone)
                gone = set(remove)
                new = [] if insert is None else insert.id.tolist()
                track.loaded = [i for i in track.loaded if i not in gone] + new
            done.set_result(reply)

        self.spawn(go(), f"update-{track.robot}")
        track.inflight.add(done)
        done.add_done_callback(track.inflight.discard)
        return await asyncio.shield(done)


def _raise_failure(failure: BaseException | None) -> None:
    """What a motion's streaming failed with, for its waiters: a failure on the bus means the data plane
    may have run out of its TPs (MotionStopped); anything else is raised as it is."""
    if isinstance(failure, BusError):
        raise MotionStopped(f"the data plane did not take the motion's next TPs: {failure}") from None
    if failure is not None:
        raise failure
