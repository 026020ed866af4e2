"""The industrial controller: plans motions and streams them into the data plane's tables.

It never commands a joint: it loads TPs, sets switcher entries and registers,
and deletes what has been driven.  It may sit far from the data plane (10-100
ms of latency and jitter); what the robots see does not depend on that,
because each motion is loaded ahead of time:

- a motion is cut into TP sections (cell.controller.tps) and loaded in
  episodes of n TPs; when a robot enters episode k, episode k+1 goes in and
  episode k-2 comes out, so at most 3n TPs per robot are loaded (expired,
  active, upcoming) and the controller has a whole episode's time to deliver
  the next one;
- a motion starts at an absolute data-plane time (registers), so robots
  started together step together; a merged entity steps as one;
- re-planning branches off at a TP far enough ahead (the measured round trip
  plus planning time, binned to sections) through TrajectorySwitcher, from a
  start state predicted with the paper's formula (Sec. 6.1);
- a stop switches the robots' registers at once to a stop trajectory planned
  from their last status;
- the controller watches the data plane (supervise()): a data plane that stops
  answering, comes back with new (empty) tables, or drops a robot's trajectory
  because the robot protective-stopped, ends the motions it carried: whoever
  waits on them gets MotionStopped with the reason at once, and the next
  motion plans from where the robots are measured to stand.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from cell.bus import Bus, BusError, BusTimeout, RemoteError, Subscription
from cell.config import CellConfig
from cell.controller import prepared
from cell.controller.loop import LoopModel
from cell.controller.plan import Motion, MotionLimits, PlanError, plan_joint, plan_linear, plan_stop
from cell.controller.tps import Sections, cut
from cell.dataplane.client import DataplaneClient
from cell.dataplane.tables import TPBatch
from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics
from cell.v1 import controller_pb2, dataplane_pb2, robot_pb2

_ID_SPACE = 2**32
STOP_JERK = 1000.0  # rad/s^3: a stop reaches full deceleration in a few ms
SWITCH_MARGIN_NS = 20_000_000  # a switch entry must be in place this long before its TP
TIDY_NS = 20_000_000  # after a motion's end, when its TPs are deleted
STOP_RATE_HZ = 20.0  # TPs of a stop: sections still long enough to fit them to the loop
# a holding TP's section: how often it steps onto itself.  A motion's final hold once took its last
# section's duration, which can be a fraction of a millisecond: then the resting robot's hold stepped
# on every status packet, a storm of resubmits costing the data plane CPU for nothing
HOLD_S = 1.0
STALE_STATUS_NS = 50_000_000  # a robot's status older than this: no command reached it, it stands
WATCH_S = 0.1  # how often supervise() reads the data plane's registers
RETRY_READ_S = 0.5  # a read of the data plane's state unanswered this long is asked again
DEAD_S = 0.5  # a data plane silent this long has lost the motions it carried (for us)
STATE_TIMEOUT_S = 0.25  # one read of its state: two unanswered in a row (with the pause) make DEAD_S

log = logging.getLogger("cell.controller")


class MotionStopped(Exception):
    """The motion was cut short by a stop (or replaced by a re-plan)."""


@dataclass
class MotionResult:
    start_ns: int  # data-plane clock
    end_ns: int
    q_end: np.ndarray  # where the plan ends (rad)


@dataclass
class Switch:
    """The last re-plan: where it branched, and the start state it predicted there."""

    branch_tp: int
    t_branch_ns: int  # data-plane clock
    lead_ms: float  # how long before the branch the switch entry was in place
    q_pred: np.ndarray
    v_pred: np.ndarray


class Link:
    """The data-plane clock as seen from here, and the round trip to it, measured on every read."""

    def __init__(self, dp: DataplaneClient) -> None:
        self.dp = dp
        self.offset_ns = 0
        self.realtime_offset_ns: int | None = None  # the cell clock less the data plane's (exact)
        self.boot_id: int | None = None  # the data plane's start (DataplaneState.boot_id)
        self._best_rtt = None  # the offset comes from the read with the shortest round trip
        self.rtts: deque[int] = deque(maxlen=32)

    async def state(
        self, robot_ids: Sequence[int] = (), timeout: float | None = None
    ) -> dataplane_pb2.DataplaneState:
        """The robots' registers and last status (all robots, or those given), no counters.

        A read, so a request lost on the way (a connection of the data plane's made anew as it
        came back from a hang) is asked again once, within the same timeout."""
        total = timeout or self.dp.timeout or self.dp.bus.config.request_timeout_s
        first = RETRY_READ_S if total >= 2 * RETRY_READ_S else total  # (a short poll is not retried)
        t0 = time.monotonic_ns()
        try:
            st = await self.dp.state(robot_ids, robots_only=True, timeout=first)
        except BusTimeout:
            if first >= total:
                raise
            t0 = time.monotonic_ns()
            st = await self.dp.state(robot_ids, robots_only=True, timeout=total - first)
        t1 = time.monotonic_ns()
        if st.boot_id != self.boot_id:  # a new data plane: its clock may differ, measure afresh
            self._best_rtt = None
            self.boot_id = st.boot_id
        if st.realtime_offset_ns:
            self.realtime_offset_ns = st.realtime_offset_ns
        rtt = t1 - t0
        self.rtts.append(rtt)
        if self._best_rtt is None or rtt <= self._best_rtt * 1.5:
            self._best_rtt = rtt if self._best_rtt is None else min(rtt, self._best_rtt)
            self.offset_ns = st.now_ns - (t0 + t1) // 2
        return st

    def now(self) -> int:
        return time.monotonic_ns() + self.offset_ns

    @property
    def rtt_ns(self) -> int:
        """A pessimistic round trip: the largest of the recent ones."""
        return max(self.rtts) if self.rtts else 50_000_000

    async def sleep_until(self, t_ns: int) -> None:
        delay = (t_ns - self.now()) / 1e9
        if delay > 0:
            await asyncio.sleep(delay)


@dataclass
class Segment:
    """A motion as loaded: its TP ids and its start on the data-plane clock."""

    start_ns: int
    motion: Motion
    sections: Sections
    ids: list[int]  # one per section, then the final hold (a self-loop at the end position)
    tick0: int | None = None  # the robot's status period in its window at start_ns (None: unknown)
    robot: int = 0  # whose tick grid start_ns is on (with tick0)

    def __post_init__(self) -> None:
        s = self.sections
        assert len(self.ids) == len(s) + 1
        self.q = np.vstack([s.q, s.q[-1:]])  # the TPs' positions, velocities and durations
        self.v = np.vstack([s.v_ff, np.zeros_like(s.v_ff[-1:])])
        self.d = np.append(s.duration, HOLD_S)

    def t_ns(self, k: int) -> int:
        """When section k ends (data-plane clock)."""
        return self.start_ns + int(self.sections.t_end[k] * 1e9)

    @property
    def end_ns(self) -> int:
        return self.t_ns(len(self.sections) - 1)


@dataclass
class Track:
    """One entity as the controller drives it: a robot, or robots merged to move as one."""

    robot: int  # the id the data plane knows the entity by (the first robot of a merged one)
    robots: list[int]
    limits: MotionLimits
    next_id: int = 1
    q_hold: np.ndarray | None = None  # where it holds after its last motion (None: not started)
    loaded: list[int] = field(default_factory=list)  # TP ids of this track in the tables
    segment: Segment | None = None
    task: asyncio.Task | None = None  # the motion being streamed
    inflight: set[asyncio.Task] = field(default_factory=set)  # its updates, which always finish
    starting: asyncio.Lock = field(default_factory=asyncio.Lock)  # motions start one after another
    stop_reason: str | None = None  # why its last motion ended early (for MotionStopped)
    generation: int = 0  # bumped when its TPs are lost: bookkeeping of older updates is void
    epoch: int = 0  # bumped by every stop or loss: an `arrive` waiting across one answers stopped
    loaded_ns: int = 0  # when (data-plane clock) its current TPs went in: older drops are old news
    loads: int = 0  # registers set by this controller so far (a flush decided before one must not follow it)

    @property
    def joints(self) -> int:
        return self.limits.v_max.size

    def take_ids(self, n: int) -> list[int]:
        ids = [(self.next_id + i) % _ID_SPACE for i in range(n)]
        self.next_id = (self.next_id + n) % _ID_SPACE
        return ids


class Controller:
    def __init__(self, bus: Bus, config: CellConfig, service: str = "dataplane") -> None:
        self.config = config
        self.bus = bus
        self.dp = DataplaneClient(bus, service)
        self.link = Link(self.dp)
        cc = config.controller
        self.rate_hz, self.fine_hz, self.episode = cc.tp_rate_hz, cc.fine_rate_hz, cc.episode
        self.lead_ns = int(cc.lead_s * 1e9)
        dpc = config.dataplane
        self.gain = np.array(dpc.c2) / np.array(dpc.c1)  # see cell.controller.tps
        self.kin = Kinematics()
        lim = arm_model().limits
        self.arm_limits = MotionLimits(
            v_max=np.minimum(lim.v_max, np.array(dpc.v_max)),
            a_max=np.minimum(lim.a_max, np.array(cc.a_max)),
            j_max=np.array(cc.j_max),
            tool_v_max=cc.tool_v_max,
            tool_a_max=cc.tool_a_max,
            tool_j_max=cc.tool_j_max,
            tool_w_max=cc.tool_w_max,
        )
        self.tracks: dict[int, Track] = {}
        self.plan_ns = 100_000_000  # how long planning a re-plan takes (measured, pessimistic)
        self.late_starts = 0  # motions whose first TPs were in place only after their start time
        self.last_switch: Switch | None = None
        self.unfinished: dict[int, tuple] = {}  # robot -> the motion a stop interrupted (for resume)
        self.stopped: set[int] = set()  # robots stopped over the Responsive Link, until released
        self.lost: list[tuple[float, str]] = []  # (monotonic s, reason) of each loss, for the record
        self._dropped_seen: dict[int, int] = {}  # robot -> the data plane's dropped_ns last seen
        # set while supervise() has the tables in hand: motions wait for it (a take-over's flush
        # must not sweep away a motion loaded meanwhile); None: not supervised (tests, benches)
        self.tables_ready: asyncio.Event | None = None
        # robot -> its track's `loads` when its TPs were last lost: supervise() flushes them once it can,
        # unless a motion was loaded since (a flush decided before a load must never land after it)
        self.pending_flush: dict[int, int] = {}
        self.loading = asyncio.Lock()  # held around every update that sets registers, and every flush
        # robot -> (window origin, cell clock ns; status period ns; periods a window): its tick grid,
        # from its announcements (see grid_start())
        self.grids: dict[int, tuple[int, int, int]] = {}
        self._asked: set[int] = set()  # robots asked for their announcement (see know_grid())
        # motions prepared ahead (cell.controller.prepared): loops under way, alternates loaded for a
        # robot's running motion, and the start of each robot of the last armed start
        self.loops: dict[int, prepared.LoopRun] = {}
        self.alternates: dict[int, tuple[Segment, dict[str, list[prepared.Alternate]]]] = {}
        self.last_fire: dict[int, int] = {}
        self._announcements: asyncio.Task | None = None

    # --- robots ------------------------------------------------------------------------------

    def robot_id(self, robot: int | str) -> int:
        if isinstance(robot, int):
            return robot
        return self.config.robot(robot).id

    def track(self, robot: int | str) -> Track:
        rid = self.robot_id(robot)
        for t in self.tracks.values():
            if rid in t.robots:
                return t
        t = Track(rid, [rid], self.arm_limits)
        self.tracks[rid] = t
        return t

    async def merge(self, robots: list[int | str]) -> Track:
        """Drive several robots as one entity (their joints side by side): they step together."""
        ids = [self.robot_id(r) for r in robots]
        old = [self.track(r) for r in ids]
        for t in old:
            if t.task is not None and not t.task.done():
                raise PlanError(f"robot {t.robot} is moving; stop it before merging")
        # the robots let go of their own TPs first (they hold where they stand, commanded 0)
        held = [t for t in old if t.loaded]
        if held:
            await self.dp.update(
                remove=[(t.robot, i) for t in held for i in t.loaded],
                registers=[(t.robot, None, 0) for t in held],
            )
        q_hold = [t.q_hold for t in old]
        await self.dp.merge(ids)
        lim = self.arm_limits
        n = len(ids)
        merged = MotionLimits(
            np.tile(lim.v_max, n), np.tile(lim.a_max, n), np.tile(lim.j_max, n),
            lim.tool_v_max, lim.tool_a_max, lim.tool_j_max, lim.tool_w_max,
        )  # fmt: skip
        for rid in ids:
            self.tracks.pop(rid, None)
        track = Track(ids[0], ids, merged)
        if all(q is not None for q in q_hold):
            track.q_hold = np.concatenate(q_hold)  # type: ignore[arg-type]
        self.tracks[ids[0]] = track
        return track

    async def joints_now(self, track: Track) -> tuple[np.ndarray, np.ndarray, int]:
        """The last status of the track's robots: positions, velocities, its data-plane time."""
        st = await self.link.state(track.robots)
        status = _status_of(track, {r.robot_id: r for r in st.robots})
        if status is None:
            raise PlanError(f"no status from robot(s) {track.robots} at the data plane yet")
        return status

    def loop(self, track: Track) -> LoopModel:
        """The closed loop the track's TPs drive (cell.controller.loop)."""
        rid = track.robots[0]
        robot = next((r for r in self.config.robots if r.id == rid), None)
        status_hz, command_hz = (500, 125) if robot is None else (robot.status_hz, robot.command_hz)
        dpc, n = self.config.dataplane, track.joints
        return LoopModel(
            c1=np.resize(np.array(dpc.c1), n),
            c2=np.resize(np.array(dpc.c2), n),
            v_max=np.resize(np.array(dpc.v_max), n),
            a_max=np.resize(arm_model().limits.a_max, n),
            status_s=1.0 / status_hz,
            window=status_hz // command_hz,
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
        track = robot if isinstance(robot, Track) else self.track(robot)
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
        except BusError as exc:
            raise _untaken(exc) from None

    async def arrive(
        self, robot: int | str, tolerance: float = 2e-4, timeout: float = 10.0
    ) -> tuple[np.ndarray, int]:
        """Until the robot has ended its motions and stands within `tolerance` (rad, every joint) of
        where they end; its measured joints and their data-plane time.  (V+'s BREAK.)"""
        track = self.track(robot)
        await self.wait_idle(track)
        if track.stop_reason:  # its last motion ended early (lost or stopped before we were asked):
            why, track.stop_reason = track.stop_reason, None  # it will not arrive where that motion
            raise MotionStopped(why)  # was to end; said once (the next break finds it standing)
        epoch = track.epoch
        async with asyncio.timeout(timeout):
            while True:
                if track.epoch != epoch:  # stopped or lost while we waited for it to settle
                    raise MotionStopped(track.stop_reason or "the robot was stopped")
                q, v, t_ns = await self.joints_now(track)
                goal = track.q_hold if track.q_hold is not None else q
                if np.abs(q - goal).max() <= tolerance and np.abs(v).max() <= 10 * tolerance:
                    return q, t_ns
                await asyncio.sleep(0.01)

    async def _move(
        self, robot: int | str, plan: Callable[[Track, np.ndarray], Motion], fine: bool, wait: bool
    ) -> MotionResult:
        """Plan from where the robot will be and start; motions of one robot start in call order,
        each after the one before (a queue).  With wait, return when the motion has ended; else
        once it is loaded and its start time set."""
        track = self.track(robot)
        async with track.starting:
            self.check_running(track)
            q0 = await self.start_q(track)
            result, tracks = await self.launch({track.robot: plan(track, q0)}, fine)
        return await self.finish(tracks, result) if wait else result

    async def move_joints(
        self, robot: int | str, q_goal: np.ndarray, speed: float = 1.0, fine: bool = False, wait: bool = True
    ) -> MotionResult:
        goal = np.asarray(q_goal, np.float64)

        def plan(track: Track, q0: np.ndarray) -> Motion:
            self.unfinished[track.robot] = ("joints", goal, speed, fine)
            return plan_joint(q0, goal, track.limits.scaled(speed))

        return await self._move(robot, plan, fine, wait)

    async def move_to(
        self,
        robot: int | str,
        pos: np.ndarray,
        rot: np.ndarray,
        speed: float = 1.0,
        fine: bool = False,
        wait: bool = True,
    ) -> MotionResult:
        """A joint-space motion to a tool pose (IK nearest the joints it starts from)."""

        def plan(track: Track, q0: np.ndarray) -> Motion:
            goal = self.kin.ik(pos, rot, q0)
            self.unfinished[track.robot] = ("joints", goal, speed, fine)
            return plan_joint(q0, goal, track.limits.scaled(speed))

        return await self._move(robot, plan, fine, wait)

    async def move_linear(
        self,
        robot: int | str,
        pos: np.ndarray,
        rot: np.ndarray,
        speed: float = 1.0,
        fine: bool = False,
        wait: bool = True,
    ) -> MotionResult:
        """The tool along a straight line to (pos, rot)."""

        def plan(track: Track, q0: np.ndarray) -> Motion:
            self.unfinished[track.robot] = ("linear", (pos, rot), speed, fine)
            return plan_linear(self.kin, q0, pos, rot, track.limits.scaled(speed))

        return await self._move(robot, plan, fine, wait)

    async def move_together(
        self, goals: dict[int | str, np.ndarray], speed: float = 1.0, fine: bool = False
    ) -> MotionResult:
        """Several robots (or merged entities) to joint goals, started at one data-plane time."""
        motions: dict[int, Motion] = {}
        for robot, q_goal in goals.items():
            track = self.track(robot)
            q0 = await self.start_q(track)
            motions[track.robot] = plan_joint(q0, np.asarray(q_goal, np.float64), track.limits.scaled(speed))
        result, tracks = await self.launch(motions, fine)
        return await self.finish(tracks, result)

    async def resume(self, robot: int | str) -> MotionResult | None:
        """After a stop: the interrupted motion's goal, re-planned from where the robot stands
        (None if nothing was interrupted)."""
        track = self.track(robot)
        left = self.unfinished.get(track.robot)
        if left is None:
            return None
        kind, target, speed, fine = left
        if kind == "linear":
            pos, rot = target
            return await self.move_linear(robot, pos, rot, speed, fine)
        return await self.move_joints(robot, target, speed, fine)

    def pose_of(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.kin.fk(q[:6])

    async def execute(self, motions: dict[int, Motion], fine: bool = False) -> MotionResult:
        """Start the motions at one shared data-plane time and return when all have ended."""
        result, tracks = await self.launch(motions, fine)
        return await self.finish(tracks, result)

    async def tables_in_hand(self) -> None:
        """Until supervise() has the data plane's tables in hand (its take-over at our start, or after
        a loss, clears them: a motion loaded before would be swept away)."""
        if self.tables_ready is not None and not self.tables_ready.is_set():
            try:
                async with asyncio.timeout(self.config.bus.request_timeout_s):
                    await self.tables_ready.wait()
            except TimeoutError:
                raise MotionStopped("the data plane is not answering: no motion can start") from None

    async def launch(
        self, motions: dict[int, Motion], fine: bool = False
    ) -> tuple[MotionResult, list[Track]]:
        """Load the motions' first episodes and start them at one data-plane time, in one atomic
        update; they stream on in the background."""
        rate = self.fine_hz if fine else self.rate_hz
        await self.tables_in_hand()
        planned = []
        for robot, motion in motions.items():
            track = self.track(robot)
            self.check_running(track)
            # (in a worker thread: fitting a long motion's TPs takes 0.1-0.5 s of CPU, which would hold
            # up everything else this controller does, its watch on the data plane too)
            sections = await asyncio.to_thread(
                cut, motion, rate, np.resize(self.gain, track.joints), self.loop(track), tick0=0
            )
            planned.append((track, motion, sections, track.take_ids(len(sections) + 2)))
        # the start time is set once the planning is done, so that the lead only has to cover the
        # update's way to the data plane (planning first would eat it on a busy host: a late start)
        await self.know_grid(planned[0][0].robot)
        await self.link.state()  # a fresh clock and round trip
        start, at, tick0 = self.grid_start(
            planned[0][0].robot, self.link.now() + self.lead_ns + 2 * self.link.rtt_ns
        )
        first: list[TPBatch] = []
        registers, remove, segments = [], [], []
        for track, motion, sections, (hold_id, *ids) in planned:
            q0 = motion.sample(np.array([0.0]))[0][0]
            # (the other robots of a shared start have grids of their own: phase unknown to the fit)
            phase = tick0 if track is planned[0][0] else None
            seg = Segment(start, motion, sections, ids, phase, track.robot)
            first.append(self._hold_batch(track, hold_id, ids[0], q0))
            first.append(self._batch(track, seg, 0, min(self.episode, len(ids))))
            registers.append((track.robot, hold_id, at))
            remove += [(track.robot, i) for i in track.loaded]
            segments.append((track, seg, hold_id))
        try:
            async with self.loading:
                reply = await self.dp.update(insert=_concat(first), remove=remove, registers=registers)
                for track, _, _ in segments:
                    track.loads += 1
        except RemoteError as exc:
            if exc.code == "stopped":  # stopped on the link before we heard of it
                raise MotionStopped(exc.message) from None
            raise
        except BusError as exc:  # it may yet be applied, late: it must not start unseen
            tracks = [t for t, _, _ in planned]
            self.lose(tracks, f"the data plane did not confirm the motion's start: {exc}")
            self.pending_flush.update({r: t.loads for t in tracks for r in t.robots})
            raise MotionStopped(tracks[0].stop_reason or str(exc)) from None
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
            track.loaded = [hold_id, *seg.ids[: self.episode]]
            track.segment = seg
            track.q_hold = None  # moving: where it ends is the segment's end
            track.task = asyncio.ensure_future(self._stream(track, seg, 1))
            self._publish_plan(track, seg)
        end = max(seg.end_ns for _, seg, _ in segments)
        q_end = np.concatenate([seg.sections.q[-1] for _, seg, _ in segments])
        return MotionResult(start, end, q_end), [t for t, _, _ in segments]

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
        except BusError as exc:
            raise _untaken(exc) from None
        for track in tracks:
            self.unfinished.pop(track.robot, None)
        return result

    async def _stream(self, track: Track, seg: Segment, next_episode: int) -> None:
        """Load episode after episode ahead of the robot; then tidy up behind it."""
        n = self.episode
        ids = seg.ids
        k = next_episode
        while k * n < len(ids):
            # when the robot enters episode k-1, episode k goes in and episode k-3 comes out
            await self.link.sleep_until(seg.t_ns(max(0, (k - 1) * n - 1)) if k > 1 else seg.start_ns)
            keep = set(ids[(k - 2) * n :]) | self._prepared_ids(track, seg) if k >= 2 else set()
            old = [i for i in track.loaded if i not in keep] if k >= 2 else []
            await self._apply(track, self._batch(track, seg, k * n, min((k + 1) * n, len(ids))), old)
            k += 1
        # all but the final hold go once the robot is on it (our view of the data-plane clock may be
        # off by half a round trip: a deletion that comes too early is refused as in_use; retry)
        await self.link.sleep_until(seg.end_ns + self.link.rtt_ns + TIDY_NS)
        old = [i for i in track.loaded if i != ids[-1]]
        for attempt in range(20):
            try:
                if old:
                    await self._apply(track, None, old)
                break
            except RemoteError as exc:
                if exc.code != "in_use" or attempt == 19:
                    raise
                await asyncio.sleep(TIDY_NS / 1e9)
        track.q_hold = seg.sections.q[-1].copy()

    def _prepared_ids(self, track: Track, seg: Segment) -> set[int]:
        """The TPs of alternates prepared for this segment: streaming leaves them loaded."""
        main, branches = self.alternates.get(track.robot, (None, {}))
        if main is not seg:
            return set()
        return {i for alts in branches.values() for a in alts for i in a.segment.ids[: self.episode]}

    async def _apply(
        self,
        track: Track,
        insert: TPBatch | None,
        remove: list[int],
        switches: list[tuple[int, int, int | None]] | None = None,
    ) -> dataplane_pb2.UpdateReply:
        """One update of a track's TPs with its bookkeeping, carried through even if the caller is
        cancelled (a stop): the controller always knows what it has loaded."""

        generation = track.generation

        async def go() -> dataplane_pb2.UpdateReply:
            reply = await self.dp.update(
                insert=() if insert is None else insert,
                remove=[(track.robot, i) for i in remove],
                switches=switches or [],
            )
            if track.generation == generation:  # (else the tables it went into are gone)
                gone = set(remove)
                new = [] if insert is None else insert.id.tolist()
                track.loaded = [i for i in track.loaded if i not in gone] + new
            return reply

        task = asyncio.ensure_future(go())
        track.inflight.add(task)
        task.add_done_callback(track.inflight.discard)
        return await asyncio.shield(task)

    async def _halt(self, track: Track) -> None:
        """Stop streaming the track's motion; wait for its updates in flight."""
        if track.task is not None and not track.task.done():
            track.task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await track.task
        if track.inflight:
            await asyncio.gather(*track.inflight, return_exceptions=True)

    async def aclose(self) -> None:
        """Stop streaming (the robots hold where their loaded TPs take them) and wait for it."""
        if self._announcements is not None:
            self._announcements.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._announcements
            self._announcements = None
        for t in list(self.tracks.values()):
            await self._halt(t)

    async def __aenter__(self) -> Controller:
        sub = await self.bus.subscribe("announce/robot/")
        self._announcements = asyncio.ensure_future(self._follow_announcements(sub))
        return self

    async def _follow_announcements(self, sub: Subscription) -> None:
        """Keep each robot's tick grid (RobotAnnounce.window_origin_ns) as robots (re)announce."""
        while True:
            for env in await sub.recv_batch():
                with contextlib.suppress(Exception):  # (a malformed one is the bus's to count)
                    a = env.decode(robot_pb2.RobotAnnounce)
                    self._take_announcement(a)

    def _take_announcement(self, a: robot_pb2.RobotAnnounce) -> None:
        if a.window_origin_ns and a.status_hz and a.command_hz:
            w = max(1, a.status_hz // a.command_hz)
            self.grids[a.robot_id] = (a.window_origin_ns, round(1e9 / a.status_hz), w)

    async def know_grid(self, robot: int) -> None:
        """The robot's tick grid, asked of it once if no announcement has come yet (a controller
        that has just come up would otherwise start its first motions off the grid); a robot that
        does not answer within a second is driven without one."""
        if robot in self.grids or robot in self._asked:
            return
        self._asked.add(robot)
        name = next((r.name for r in self.config.robots if r.id == robot), None)
        if name is None:
            return
        with contextlib.suppress(BusError, ValueError):
            a = await self.bus.request(
                f"robot/{name}", "announce", robot_pb2.AnnounceRequest(), robot_pb2.RobotAnnounce, timeout=1.0
            )
            self._take_announcement(a)

    def grid_start(self, robot: int, earliest_ns: int) -> tuple[int, int, int | None]:
        """When to start a motion of the robot at or after earliest_ns (data-plane clock):
        (plan start, register time, the model's window phase there).

        The data plane steps a trajectory at the first status after the register's time, and
        the robot keeps the answer to its window's last status: a start between two statuses,
        or in another window phase than the TPs were fitted for, puts the robot up to a status
        period behind the plan and its commands up to a window off (about 1 mm at the tool in a
        brisk move).  So a motion starts on a status period that begins a command window, its
        register a quarter period earlier (the status comes a little after it is due), and the
        TPs are fitted for phase 0.  Robots not heard announcing start at earliest_ns as before.
        """
        grid = self.grids.get(robot)
        if grid is None:
            return earliest_ns, earliest_ns, None
        origin_rt, period, w = grid
        # the grid is on the cell clock; the data plane says how its clock stands to that exactly
        # (going through our own clock and the offset estimated over the bus is up to half a
        # round trip off: a start a fraction of a period off the grid, tenths of a mm at the tool)
        rt = self.link.realtime_offset_ns
        if rt is None:
            rt = (time.time_ns() - time.monotonic_ns()) - self.link.offset_ns
        origin = origin_rt - rt
        window = period * w
        k = -(-(earliest_ns + period // 4 - origin) // window)  # the next window's start
        start = origin + k * window
        return start, start - period // 4, 0

    def phase_at(self, seg: Segment, t_ns: int) -> int:
        """The model's window phase at a time on a segment started on its robot's grid (else 0)."""
        grid = self.grids.get(seg.robot)
        if seg.tick0 is None or grid is None:
            return 0
        _, period, w = grid
        return (seg.tick0 + round((t_ns - seg.start_ns) / period)) % w

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def _publish_plan(self, track: Track, seg: Segment) -> None:
        """The segment's plan on plan/<robot>, one message per robot of the track."""
        s = seg.sections
        t = np.concatenate([[seg.start_ns], seg.start_ns + np.rint(s.t_end * 1e9).astype(np.int64)])
        q0, v0 = seg.motion.sample(np.array([0.0]))
        q = np.vstack([q0, s.q])
        v = np.vstack([v0, s.q_plan_v])
        for i, rid in enumerate(track.robots):
            robot = next((r for r in self.config.robots if r.id == rid), None)
            if robot is None:
                continue
            cols = slice(6 * i, 6 * i + 6)
            msg = controller_pb2.Plan(
                robot_id=rid,
                joints=6,
                t_ns=t.tolist(),
                positions=q[:, cols].ravel().tolist(),
                velocities=v[:, cols].ravel().tolist(),
            )
            self.dp.bus.publish(f"plan/{robot.name}", msg)

    def _batch(self, track: Track, seg: Segment, lo: int, hi: int) -> TPBatch:
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

    def _hold_batch(
        self, track: Track, hold_id: int, next_id: int, q: np.ndarray, duration_s: float = HOLD_S
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

    # --- the data plane's faults -----------------------------------------------------------------

    async def supervise(self) -> None:
        """Watch the data plane for as long as the controller runs (see the module's docstring).

        The first answer is a take-over: whatever an earlier controller left in the tables goes
        (robots in motion get a stop planned from their status).  Every later loss of the tables,
        for whatever reason, ends the motions they carried and flushes what is left of them."""
        self.tables_ready = ready = asyncio.Event()
        boot: int | None = None
        # silence counts from the last answer (or our start): one slow answer is no verdict
        silent_since = time.monotonic()
        gone = False  # the motions were declared lost for silence; flush once it answers again
        while True:
            try:
                st = await self.link.state(timeout=STATE_TIMEOUT_S)
            except BusError:
                now = time.monotonic()
                if not gone and now - silent_since >= DEAD_S:
                    gone = True
                    ready.clear()
                    self.lose(
                        list(self.tracks.values()),
                        f"the data plane stopped answering ({now - silent_since:.1f} s): "
                        "its motions are lost",
                    )
                await asyncio.sleep(WATCH_S)
                continue
            silent_since = time.monotonic()
            if boot is None or st.boot_id != boot or gone:
                if boot is not None and st.boot_id != boot:
                    ready.clear()
                    self.lose(list(self.tracks.values()), "the data plane restarted: its tables were lost")
                with contextlib.suppress(BusError):
                    # at our start robots may be moving on an earlier controller's TPs: stop them; after a
                    # loss they went without commands and stand in a protective stop: hold them there
                    # (a stop planned from the status registers of a data plane that just came back
                    # could start from a status it had queued before it went away)
                    await self.take_over(plan_stops=boot is None and not gone)
                    boot, gone = st.boot_id, False
                    self._dropped_seen = {r.robot_id: r.dropped_ns for r in st.robots}
                    ready.set()
                await asyncio.sleep(WATCH_S)
                continue
            for r in st.robots:
                seen = self._dropped_seen.get(r.robot_id, 0)
                self._dropped_seen[r.robot_id] = r.dropped_ns
                track = self.track(r.robot_id)
                if r.dropped_ns > seen and r.dropped_ns >= track.loaded_ns:  # (not what it carries now)
                    why = _DROPPED.get(r.dropped_why, "the data plane dropped its trajectory")
                    self.lose([track], f"robot {r.robot_id} stopped: {why}")
                    self.pending_flush.update({rid: track.loads for rid in track.robots})
            if self.pending_flush:
                with contextlib.suppress(BusError):
                    await self._flush_lost()
            await asyncio.sleep(WATCH_S)

    async def _flush_lost(self) -> None:
        """Remove the TPs of lost motions from the tables, for the robots not loaded anew since."""
        async with self.loading:
            robots = sorted(r for r, loads in self.pending_flush.items() if self.track(r).loads == loads)
            if robots:
                await self.dp.update(flush=robots)
            self.pending_flush.clear()

    def lose(self, tracks: list[Track], reason: str) -> None:
        """The tables no longer hold these tracks' TPs: end their motions (MotionStopped(reason) to
        whoever waits), forget what was loaded, and plan the next motion from the measured state."""
        hit = [t for t in tracks if (t.task is not None and not t.task.done()) or t.loaded]
        for t in hit:
            t.stop_reason = reason
            t.generation += 1
            t.epoch += 1
            if t.task is not None and not t.task.done():
                t.task.cancel()
            t.loaded, t.segment, t.q_hold = [], None, None
        if hit:
            self.lost.append((time.monotonic(), reason))
            log.warning("%s (robots %s)", reason, sorted(r for t in hit for r in t.robots))

    async def take_over(self, plan_stops: bool = True) -> None:
        """Flush every configured robot's TPs (an earlier controller's, or a lost set); with plan_stops,
        stop the robots that are moving from their measured state, else they hold (commands of 0)."""
        robots = {r.id for r in self.config.robots} | {r for t in self.tracks.values() for r in t.robots}
        for t in self.tracks.values():
            await self._halt(t)
        if plan_stops:
            await self.stop(sorted(robots), flush=True)
            for t in self.tracks.values():  # what it stopped was an earlier controller's motion, not one
                t.stop_reason = None  # of ours: a first `break` finds the robot standing, not "stopped"
        else:
            async with self.loading:
                await self.dp.update(flush=sorted(robots))

    # --- stops ---------------------------------------------------------------------------------

    async def stopped_on_link(self, robot: int) -> None:
        """A robot was stopped over the Responsive Link (the data plane has cleared its registers and
        ramps it down): stop streaming its motion (MotionStopped to whoever waits) and unload it."""
        self.stopped.add(robot)
        track = self.track(robot)
        track.stop_reason = f"robot {robot} was stopped over the Responsive Link"
        track.epoch += 1
        await self._halt(track)
        if track.loaded:
            with contextlib.suppress(RemoteError):
                await self._apply(track, None, list(track.loaded))
        track.segment, track.q_hold = None, None  # the next motion starts where the robot stands

    def released_on_link(self, robot: int) -> None:
        self.stopped.discard(robot)

    def check_running(self, track: Track) -> None:
        held = [r for r in track.robots if r in self.stopped]
        if held:
            raise MotionStopped(f"robot(s) {held} stopped over the Responsive Link: resume first")

    async def stop(
        self, robots: list[int | str] | None = None, flush: bool = False
    ) -> dict[int, MotionResult]:
        """Protective stop: the robots decelerate within their limits from where they are, taking
        effect at the data plane's next packet after this update (within one command window).  With
        flush, every TP of these robots goes first, also those this controller did not load."""
        if robots is None:
            tracks = list(self.tracks.values())
        else:
            tracks = list({id(t): t for t in map(self.track, robots)}.values())
        for t in tracks:
            await self._halt(t)
        st = await self.link.state()
        by_id = {r.robot_id: r for r in st.robots}
        apply_ns = self.link.now() + self.link.rtt_ns
        batches, registers, remove, results = [], [], [], {}
        for t in tracks:
            status = _status_of(t, by_id)
            if status is None or any(r in self.stopped for r in t.robots):
                continue  # never heard of, or stopping on the data plane's ramp already: nothing to do
            q, v, status_ns = status
            if self.link.now() - status_ns > STALE_STATUS_NS:  # no news: it stands (its watchdog)
                v = np.zeros_like(v)
            q_pred = q + v * max(0.0, (apply_ns - status_ns) / 1e9)
            motion = plan_stop(q_pred, v, self.stop_limits(t))
            sections = cut(motion, STOP_RATE_HZ, np.resize(self.gain, t.joints), self.loop(t), v)
            ids = t.take_ids(len(sections) + 1)
            seg = Segment(apply_ns, motion, sections, ids)
            batches.append(self._batch(t, seg, 0, len(ids)))
            registers.append((t.robot, ids[0], seg.t_ns(0)))
            remove += [(t.robot, i) for i in t.loaded]
            t.loaded, t.segment, t.q_hold = list(ids), seg, sections.q[-1].copy()
            t.stop_reason, t.epoch = t.stop_reason or "the robot was stopped", t.epoch + 1
            self._publish_plan(t, seg)
            results[t.robot] = MotionResult(apply_ns, seg.end_ns, sections.q[-1].copy())
        flushed = sorted({r for t in tracks for r in t.robots}) if flush else []
        if flushed:
            remove = []
        if batches or flushed:
            insert = _concat(batches) if batches else ()
            async with self.loading:
                reply = await self.dp.update(insert=insert, remove=remove, registers=registers, flush=flushed)
                for t in tracks:
                    t.loads += 1
            for r in results.values():
                r.start_ns = reply.now_ns  # in effect from the data plane's next packet on
            for t in tracks:
                t.loaded_ns = reply.now_ns
        return results

    def stop_limits(self, track: Track) -> MotionLimits:
        """A stop brakes with the drives' full deceleration, reached at once (they limit no jerk)."""
        n = track.joints
        return replace(
            track.limits, a_max=np.resize(arm_model().limits.a_max, n) * 0.95, j_max=np.full(n, STOP_JERK)
        )

    # --- prepared ahead (cell.controller.prepared) ------------------------------------------------

    async def arm(self, goals: dict[int | str, np.ndarray], speed: float = 1.0) -> prepared.Armed:
        """Load robots' joint motions behind holds, to be started together by fire()."""
        return await prepared.arm(self, goals, speed)

    async def fire(self, armed: prepared.Armed, wait: bool = True) -> MotionResult:
        """Start armed motions with one update of switch entries."""
        return await prepared.fire(self, armed, wait)

    async def run_loop(
        self, robot: int | str, waypoints: list[np.ndarray], speed: float = 1.0, laps: int = 0
    ) -> prepared.LoopRun:
        """A lap through the waypoints loaded once as a loop, run `laps` times (0: until end_loop())."""
        return await prepared.run_loop(self, robot, waypoints, speed, laps)

    async def end_loop(self, robot: int | str) -> int:
        """End the robot's loop at the next lap end the update reaches; the laps it runs."""
        return await prepared.end_loop(self, robot)

    async def prepare_alternates(
        self, robot: int | str, goals: dict[str, np.ndarray], speed: float = 1.0, every: int = 1
    ) -> int:
        """Branches of the running motion to other goals, loaded ahead; the TPs loaded."""
        return await prepared.prepare_alternates(self, robot, goals, speed, every)

    async def take_alternate(self, robot: int | str, name: str) -> MotionResult:
        """Onto a prepared branch at the next TP in reach; returns when the branch has ended."""
        return await prepared.take_alternate(self, robot, name)

    # --- re-planning -----------------------------------------------------------------------------

    async def replan(self, robot: int | str, q_goal: np.ndarray, speed: float = 1.0) -> MotionResult:
        """Switch a moving robot onto a new motion to q_goal, branching at a TP far enough ahead."""
        track = self.track(robot)
        seg = track.segment
        if track.task is None or track.task.done() or seg is None:
            return await self.move_joints(robot, q_goal, speed)
        for _attempt in range(4):
            t_plan = time.perf_counter_ns()
            q_s, v_s, status_ns = await self.joints_now(track)
            ahead = self.link.now() + self.link.rtt_ns + self.plan_ns + SWITCH_MARGIN_NS
            ends = np.array([seg.t_ns(k) for k in range(len(seg.sections))])
            later = np.flatnonzero(ends >= ahead)
            k = int(later[0]) if later.size else -1
            if k < 0 or k >= len(seg.sections) - 1:  # too late to branch: finish, then move
                await track.task
                return await self.move_joints(robot, q_goal, speed)
            t_b = int(ends[k])
            # the paper's prediction: the plan at the branch, corrected by how far off the robot is
            t_rel = (status_ns - seg.start_ns) / 1e9
            q_traj, v_traj = seg.motion.sample(np.array([t_rel, (t_b - seg.start_ns) / 1e9]))
            dt = (t_b - status_ns) / 1e9
            q_pred = q_traj[1] + (q_s - q_traj[0]) + (v_s - v_traj[0]) * dt
            v_pred = v_traj[1]
            lim = track.limits.scaled(speed)
            motion = plan_joint(q_pred, np.asarray(q_goal, np.float64), lim, v0=v_pred)
            tick0 = self.phase_at(seg, t_b)
            sections = cut(
                motion, self.rate_hz, np.resize(self.gain, track.joints), self.loop(track), v_pred, tick0
            )
            ids = track.take_ids(len(sections) + 1)
            new = Segment(t_b, motion, sections, ids, tick0 if seg.tick0 is not None else None, seg.robot)
            took = time.perf_counter_ns() - t_plan
            self.plan_ns = max(took, int(0.7 * self.plan_ns + 0.3 * took))
            # the switch goes in while the old motion still streams; it counts only if it is in place
            # before the robot leaves the branching TP, which the data plane's clock in the reply tells
            first = self._batch(track, new, 0, min(self.episode, len(ids)))
            branch = seg.ids[k]
            reply = await self._apply(track, first, [], [(track.robot, branch, ids[0])])
            if reply.now_ns < t_b - SWITCH_MARGIN_NS // 2:
                break
            # in place late: once the branch's time has passed, the data plane says which way it went
            await self.link.sleep_until(t_b + SWITCH_MARGIN_NS // 2)
            st = await self.link.state(track.robots)
            if any(r.tp_id in ids for r in st.robots if r.robot_id == track.robot):
                break  # it took the branch after all
            await self._apply(track, None, ids[: self.episode], [(track.robot, branch, None)])
            self.plan_ns *= 2  # too slow this time: branch further ahead
        else:
            raise PlanError("could not branch off in time (the link or the planning is too slow)")
        await self._halt(track)
        self.last_switch = Switch(branch, t_b, (t_b - reply.now_ns) / 1e6, q_pred, v_pred)
        track.segment = new
        track.task = asyncio.ensure_future(self._stream(track, new, 1))
        self._publish_plan(track, new)
        await track.task
        return MotionResult(t_b, new.end_ns, sections.q[-1].copy())


def _untaken(exc: BusError) -> MotionStopped:
    """A motion's streaming failed on the bus: the data plane may have run out of its TPs."""
    return MotionStopped(f"the data plane did not take the motion's next TPs: {exc}")


_DROPPED = {
    "stop": "it was stopped over the Responsive Link (an e-stop, a stop, or a node's beacon watchdog)",
    "watchdog": "it went past its watchdog without commands (protective stop): its trajectory was dropped",
    "quiet": "no status from it for over 0.5 s (the robot, its host or its link went silent, or the data "
    "plane hung): its trajectory was dropped",
    "underrun": "its next TPs did not come in time (the controller fell behind): its trajectory was dropped",
}


def _status_of(
    track: Track, by_id: dict[int, dataplane_pb2.RobotPlaneState]
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The track's robots' last status (positions, velocities, the oldest time); None without one."""
    if any(r not in by_id or by_id[r].status_ns == 0 for r in track.robots):
        return None
    q = np.concatenate([np.array(by_id[r].position) for r in track.robots])
    v = np.concatenate([np.array(by_id[r].velocity) for r in track.robots])
    return q, v, min(by_id[r].status_ns for r in track.robots)


def _concat(batches: list[TPBatch]) -> TPBatch:
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
