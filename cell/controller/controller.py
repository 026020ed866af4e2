"""The industrial controller: plans motions and streams them into the data plane's tables.

Controller is the public face users and the controller service call: motions (move_joints,
move_to, move_linear, move_together, replan, resume), stops, waiting for arrival, merged robots,
and the motions prepared ahead (arm/fire, loops, alternates; cell.controller.prepared).  What it
loads and when is the motion schedule's (cell.controller.schedule, sans I/O).  It is a facade over
three parts, built by its constructor: the robot book (cell.controller.robots), the engine
(cell.controller.engine), which drives the schedule against the data plane in its own task group,
and the stopping (cell.controller.stopping); supervision (cell.controller.supervision) watches the
data plane for as long as the controller runs.

    async with Controller(bus, config) as ctl:
        await ctl.move_joints("r1", q_goal)
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Callable, Sequence

import numpy as np

from cell.bus import Bus, RemoteError
from cell.config import CellConfig
from cell.controller import prepared, supervision
from cell.controller.engine import Engine
from cell.controller.link import Link
from cell.controller.motion import (
    Armed,
    FollowResult,
    Goal,
    LoopRun,
    MotionKind,
    MotionResult,
    MotionState,
    MotionStopped,
    NotAtGoal,
    Segment,
    Switch,
    Track,
)
from cell.controller.plan import ChainedMotion, PlanError, SampledMotion, plan_joint, plan_linear
from cell.controller.robots import RobotBook
from cell.controller.schedule import (
    STOP_JERK,
    SWITCH_MARGIN_NS,
    branch_point,
    predict_state,
    stands_at,
    tp_batch,
)
from cell.controller.stopping import Stopping
from cell.controller.tps import Led
from cell.dataplane.client import DataplaneClient
from cell.trajectory.model import TimedMotion, Trajectory, TrajectoryError
from cell.trajectory.motion import Motion
from cell.trajectory.named import NamedStore, state_dir

log = logging.getLogger("cell.controller")

AT_START_RAD = 1e-3  # a robot this close to a trajectory's first point follows it from where it stands
MAX_NAMED = 64  # trajectories kept under names (follow_named) at once
MAX_NAMED_POINTS = 2_000_000  # and their points, all together
__all__ = [
    "STOP_JERK", "Controller", "Goal", "MotionKind", "MotionResult", "MotionState", "MotionStopped",
    "NotAtGoal", "Segment", "Track",
]  # fmt: skip


class Controller:
    """The industrial controller a task script, a service or a bench drives: motions planned, loaded
    into the data plane's tables and followed, stopped and resumed, on `bus`, for `config`'s robots,
    through the data plane serving as `service`.

    A facade over its parts, each a field: the robot book (`book`: models, grids, tracks, holds), the
    engine (`engine`: launching, streaming, switching, settling) and the stopping (`stopping`: stops,
    plans published, losses), which share the data-plane client (`dp`), its clock (`link`) and the
    lock held around every update that sets registers (`loading`)."""

    def __init__(self, bus: Bus, config: CellConfig, service: str = "dataplane") -> None:
        self.bus, self.config = bus, config
        # (an id of this run: the robots it takes over are its own at the data plane, and another
        # controller taking them is seen, not fought over)
        self.id = int.from_bytes(os.urandom(8), "little") or 1
        self.dp = DataplaneClient(bus, service, controller=self.id)
        self.link = Link(self.dp)
        self.loading = asyncio.Lock()
        self.book = RobotBook(bus, config, self.link)
        self.stopping = Stopping(bus, self.dp, self.link, self.book, self.loading)
        self.engine = Engine(bus, config, self.dp, self.link, self.book, self.stopping, self.loading)
        # name -> robot -> trajectory (follow_named), kept on disk too: a restarted controller has them
        self.store = NamedStore(state_dir(config.controller.state_dir, config.cell.name))
        self.named: dict[str, dict[int, Trajectory]] = self._restore_named()

    async def __aenter__(self) -> Controller:
        await self.engine.__aenter__()
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            await self.engine.__aexit__(*exc)
        finally:
            self.book.close()

    # --- the parts' calls a user makes ---------------------------------------------------------

    def track(self, robot: int | str) -> Track:
        return self.book.track(robot)

    def robot_id(self, robot: int | str) -> int:
        return self.book.robot_id(robot)

    async def stop(
        self, robots: Sequence[int | str] | None = None, flush: bool = False
    ) -> dict[int, MotionResult]:
        """Protective stop (cell.controller.stopping.Stopping.stop)."""
        return await self.stopping.stop(robots, flush)

    async def wait_idle(self, robot: int | str | Track) -> None:
        """Until the robot's motion under way has ended; MotionStopped if it was stopped."""
        await self.engine.wait_idle(robot)

    async def joints_now(self, track: Track) -> tuple[np.ndarray, np.ndarray, int]:
        """The last status of the track's robots: positions, velocities, its data-plane time."""
        return await self.engine.joints_now(track)

    # --- robots ------------------------------------------------------------------------------

    async def merge(self, robots: list[int | str]) -> Track:
        """Drive several robots as one entity (their joints side by side): they step together."""
        ids = [self.book.robot_id(r) for r in robots]
        old = [self.book.track(r) for r in ids]
        for t in old:
            if t.moving:
                raise PlanError(f"robot {t.robot} is moving; stop it before merging")
        # the robots let go of their own TPs first (they hold where they stand, commanded 0)
        held = [t for t in old if t.loaded]
        if held:
            await self.dp.update(
                remove=[(t.robot, i) for t in held for i in t.loaded],
                registers=[(t.robot, None, 0) for t in held],
            )
        q_hold = [t.q_hold for t in old if t.q_hold is not None]
        await self.dp.merge(ids)
        merged = self.book.limits_of(ids)
        for rid in ids:
            self.book.tracks.pop(rid, None)
        track = Track(ids[0], ids, merged)
        if len(q_hold) == len(old):  # (every robot's)
            track.q_hold = np.concatenate(q_hold)
        self.book.tracks[ids[0]] = track
        return track

    def pose_of(self, robot: int | str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The tool flange's position and rotation for the robot's joints q (its own model's)."""
        rid = self.book.robot_id(robot)
        return self.book.kinematics(rid).fk(q[: self.book.arm_of(rid).dof])

    # --- motions -----------------------------------------------------------------------------

    async def arrive(
        self, robot: int | str, tolerance: float = 2e-4, timeout: float = 10.0
    ) -> tuple[np.ndarray, int]:
        """Until the robot has ended its motions and is read standing within `tolerance` (rad, every
        joint) of where they end; its measured joints and their data-plane time.  (V+'s BREAK.)
        MotionStopped if a stop or loss ends a motion meanwhile (also one that comes while a reading
        is on its way: that reading is not of the goal's robot any more); NotAtGoal if its last motion
        ended elsewhere."""
        track = self.book.track(robot)
        # (not while the take-over at our start stops every robot: that stop would end this wait
        # with "stopped", though no motion of ours was under way; seen as a flake under load)
        await self.engine.tables_in_hand()
        await self.engine.wait_idle(track)
        if track.stop_reason:  # its last motion ended early (lost or stopped before we were asked):
            why, track.stop_reason = track.stop_reason, None  # it will not arrive where that motion
            if isinstance(track.failure, NotAtGoal):  # was to end; said once (the next break finds
                raise NotAtGoal(why)  # it standing)
            raise MotionStopped(why)
        epoch = track.epoch
        async with asyncio.timeout(timeout):
            while True:
                await self.engine.wait_idle(track)  # (a motion started meanwhile: its end is the goal)
                goal = track.q_hold  # None: no motion yet, the robot stands where it stands
                q, v, t_ns = await self.engine.joints_now(track)
                if track.epoch != epoch:  # stopped or lost while we waited (or read)
                    raise MotionStopped(track.stop_reason or "the robot was stopped")
                if track.moving or track.q_hold is not goal:
                    continue
                if stands_at(q, v, goal, tolerance):
                    return q, t_ns
                await asyncio.sleep(0.01)

    async def _move(
        self, robot: int | str, plan: Callable[[Track, np.ndarray], Motion], fine: bool, wait: bool
    ) -> MotionResult:
        """Plan from where the robot will be and start; motions of one robot start in call order,
        each after the one before (a queue).  With wait, return when the motion has ended; else
        once it is loaded and its start time set."""
        track = self.book.track(robot)
        async with track.starting:
            await self.engine.confirm_running(track)
            q0 = await self.engine.start_q(track)
            result, tracks = await self.engine.launch({track.robot: plan(track, q0)}, fine)
        return await self.engine.finish(tracks, result) if wait else result

    async def move_joints(
        self, robot: int | str, q_goal: np.ndarray, speed: float = 1.0, fine: bool = False, wait: bool = True
    ) -> MotionResult:
        goal = np.asarray(q_goal, np.float64)

        def plan(track: Track, q0: np.ndarray) -> Motion:
            self.engine.unfinished[track.robot] = Goal(MotionKind.JOINTS, goal, speed, fine)
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
            goal = self.book.kinematics(track.robot).ik(pos, rot, q0)
            self.engine.unfinished[track.robot] = Goal(MotionKind.JOINTS, goal, speed, fine)
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
            self.engine.unfinished[track.robot] = Goal(MotionKind.LINEAR, (pos, rot), speed, fine)
            return plan_linear(self.book.kinematics(track.robot), q0, pos, rot, track.limits.scaled(speed))

        return await self._move(robot, plan, fine, wait)

    async def move_together(
        self, goals: dict[int | str, np.ndarray], speed: float = 1.0, fine: bool = False
    ) -> MotionResult:
        """Several robots (or merged entities) to joint goals, started at one data-plane time."""
        motions: dict[int, Motion] = {}
        for robot, q_goal in goals.items():
            track = self.book.track(robot)
            q0 = await self.engine.start_q(track)
            motions[track.robot] = plan_joint(q0, np.asarray(q_goal, np.float64), track.limits.scaled(speed))
        result, tracks = await self.engine.launch(motions, fine)
        return await self.engine.finish(tracks, result)

    def check_trajectories(
        self, trajectories: dict[int | str, Trajectory]
    ) -> dict[int, tuple[Track, TimedMotion]]:
        """Each trajectory against its robot's limits (PlanError naming the first offending point), as
        the TimedMotion it will run as (its spline solved once: checked, then followed).  A trajectory
        planned elsewhere may use the drives' whole acceleration: the controller's own a_max (what its
        TPs track closely) is for the motions it plans."""
        checked: dict[int, tuple[Track, TimedMotion]] = {}
        for robot, traj in trajectories.items():
            track = self.book.track(robot)
            lim, arm = track.limits, self.book.arm_of(track.robot)
            timed = TimedMotion(traj)
            try:
                timed.check(arm.limits.q_min, arm.limits.q_max, lim.v_max, arm.limits.a_max)
            except TrajectoryError as exc:
                named = f" {traj.name!r}" if traj.name else ""
                raise PlanError(f"robot {track.robot}: trajectory{named}: {exc}") from None
            checked[track.robot] = (track, timed)
        return checked

    def name_trajectories(self, name: str, trajectories: dict[int | str, Trajectory]) -> None:
        """Keep checked trajectories under a name (`follow_named`, the skill servers' follow:<name>);
        a name given again is replaced.  PlanError when beyond a robot's limits, or no room."""
        keep = {rid: timed.traj for rid, (_track, timed) in self.check_trajectories(trajectories).items()}
        if name not in self.named and len(self.named) >= MAX_NAMED:
            raise PlanError(f"{MAX_NAMED} trajectories are named already: name this one as one of those")
        kept = {**self.named, name: keep}  # (the name's old trajectories replaced)
        points = sum(t.points for ts in kept.values() for t in ts.values())
        if points > MAX_NAMED_POINTS:
            raise PlanError(f"named trajectories would hold {points:,} points: at most {MAX_NAMED_POINTS:,}")
        self.store.save(name, {int(r): t for r, t in keep.items()})
        self.named[name] = keep

    def _restore_named(self) -> dict[str, dict[int, Trajectory]]:
        """The names a controller before this one kept, within today's limits (the robots still in
        the cell, MAX_NAMED names, MAX_NAMED_POINTS points)."""
        robots = {r.id for r in self.config.robots}
        named: dict[str, dict[int, Trajectory]] = {}
        points = 0
        for name, trajs in self.store.load_all().items():
            n = sum(t.points for t in trajs.values())
            if not set(trajs) <= robots or len(named) >= MAX_NAMED or points + n > MAX_NAMED_POINTS:
                log.warning(
                    "named trajectory %r not restored: its robots or its size exceed this cell's", name
                )
                continue
            named[name], points = trajs, points + n
        if named:
            log.info("restored %d named trajectories: %s", len(named), ", ".join(named))
        return named

    def named_trajectories(
        self, name: str, robots: list[int | str] | None = None
    ) -> dict[int | str, Trajectory]:
        """The trajectories kept under name (of the robots given, or all); PlanError if there are none."""
        found = self.named.get(name)
        if found is None:
            known = ", ".join(sorted(self.named)) or "none"
            raise PlanError(f"no trajectory named {name!r} (named: {known})")
        if not robots:
            return {r: t for r, t in found.items()}  # (a copy, its keys typed as the result's)
        ids = [self.book.track(r).robot for r in robots]
        missing = [r for r in ids if r not in found]
        if missing:
            raise PlanError(f"trajectory {name!r} has nothing for robot(s) {missing}")
        return {r: found[r] for r in ids}

    async def follow(
        self,
        trajectories: dict[int | str, Trajectory],
        speed: float = 0.5,
        wait: bool = True,
        replace: bool = False,
    ) -> FollowResult:
        """Trajectories planned elsewhere (cell.trajectory), one per robot, their time 0 at one
        data-plane time; each checked against its robot's limits before anything is loaded (PlanError
        naming the first offending point), cut into TPs and streamed like the controller's own motions.
        A robot not at its trajectory's first point is first brought there (a joint move at `speed`;
        all robots wait for the slowest), which a trajectory that starts moving cannot allow.
        replace: a robot under way is switched onto it on the fly (TrajectorySwitcher, as `replan`),
        through a joint move from its predicted state to the first point; one robot at a time."""
        checked = self.check_trajectories(trajectories)
        if replace:
            if len(checked) != 1:
                raise PlanError("replacing a running motion takes the trajectory of one robot")
            ((rid, (track, timed)),) = checked.items()
            await self.engine.confirm_running(track)
            if track.moving and track.segment is not None:
                if np.abs(timed.qd[0]).max() > 1e-9:
                    raise PlanError(f"robot {rid}: a trajectory that starts moving cannot replace a motion")
                lim = track.limits.scaled(speed)
                lead: list[float] = []

                def onto(q: np.ndarray, v: np.ndarray) -> Motion:
                    approach = plan_joint(q, timed.q[0], lim, v0=v)
                    lead[:] = [approach.duration]
                    return ChainedMotion([approach, timed])

                switched = await self.switch(track, onto)
                if switched is not None:
                    self.engine.unfinished.pop(rid, None)
                    out = FollowResult(
                        switched.start_ns,
                        switched.end_ns,
                        switched.q_end,
                        switched.start_ns + round(lead[0] * 1e9),
                    )
                    if wait:
                        await self.engine.finish([track], switched)
                    return out
                # too late to branch: it follows once the motion under way has ended
        approaches: dict[int, Motion | None] = {}
        for rid, (track, timed) in checked.items():
            await self.engine.confirm_running(track)
            q0 = await self.engine.start_q(track)
            off = float(np.abs(q0 - timed.q[0]).max())
            if off <= AT_START_RAD:
                approaches[rid] = None
            elif np.abs(timed.qd[0]).max() > 1e-9:
                raise PlanError(
                    f"robot {rid}: the trajectory starts moving and the robot is {off:.3g} rad from its "
                    "first point: bring it there first"
                )
            else:
                approaches[rid] = plan_joint(q0, timed.q[0], track.limits.scaled(speed))
        lead_s = max((a.duration for a in approaches.values() if a is not None), default=0.0)
        motions: dict[int, Motion] = {}
        # each fitted with led TPs (cell.controller.tps.fit_led): where the plan needs them, within
        # follow_tolerance_mm; the robots start a command window after their TPs do
        window_s = 0.0
        for rid, (track, timed) in checked.items():
            a = approaches[rid]
            window_s = window_s or self.book.loop(track).window_s
            if lead_s == 0.0:
                motions[rid] = Led(timed, window_s)
                continue
            if a is None:  # (it waits at its first point for the others' approaches)
                a = SampledMotion(np.array([0.0, lead_s]), np.vstack([timed.q[0], timed.q[0]]))
            chained = ChainedMotion([ChainedMotion([a], pad=lead_s - a.duration), timed])
            motions[rid] = Led(chained, window_s, check_from_s=lead_s)
            self.engine.unfinished.pop(
                rid, None
            )  # (a trajectory is not resumed from a stop: it is run again)
        result, tracks = await self.engine.launch(motions)
        fits = [(t.segment.sections, t.segment.motion) for t in tracks if t.segment is not None]
        out = FollowResult(
            result.start_ns,
            result.end_ns,
            result.q_end,
            result.start_ns + round((window_s + lead_s) * 1e9),
            tps_per_s=max((len(s) / max(m.duration - s.lead_s, 1e-9) for s, m in fits), default=0.0),
            deviation_mm=max((s.deviation_m * 1e3 for s, _ in fits), default=0.0),
        )
        if wait:
            await self.engine.finish(tracks, result)
        return out

    async def resume(self, robot: int | str) -> MotionResult | None:
        """After a stop: the interrupted motion's goal, re-planned from where the robot stands
        (None if nothing was interrupted)."""
        track = self.book.track(robot)
        left = self.engine.unfinished.get(track.robot)
        if left is None:
            return None
        if left.kind is MotionKind.LINEAR:
            pos, rot = left.target
            return await self.move_linear(robot, pos, rot, left.speed, left.fine)
        assert isinstance(left.target, np.ndarray)  # (JOINTS: its joints)
        return await self.move_joints(robot, left.target, left.speed, left.fine)

    async def execute(self, motions: dict[int, Motion], fine: bool = False) -> MotionResult:
        """Start the motions at one shared data-plane time and return when all have ended."""
        result, tracks = await self.engine.launch(motions, fine)
        return await self.engine.finish(tracks, result)

    # --- re-planning -----------------------------------------------------------------------------

    async def replan(self, robot: int | str, q_goal: np.ndarray, speed: float = 1.0) -> MotionResult:
        """Switch a moving robot onto a new motion to q_goal, branching at a TP far enough ahead."""
        track = self.book.track(robot)
        goal = np.asarray(q_goal, np.float64)
        if track.moving and track.segment is not None:
            lim = track.limits.scaled(speed)
            switched = await self.switch(track, lambda q, v: plan_joint(q, goal, lim, v0=v))
            if switched is not None:
                return await self.engine.finish([track], switched)
            await self.engine.wait_idle(track)  # too late to branch: finish, then move
        return await self.move_joints(robot, goal, speed)

    async def switch(
        self, track: Track, plan: Callable[[np.ndarray, np.ndarray], Motion]
    ) -> MotionResult | None:
        """Branch the track's running motion, at a TP far enough ahead, onto plan(q, v) from the state
        predicted there; once in place, the new motion streams on.  None if it is too late to branch
        (the running motion ends first)."""
        seg = track.segment
        assert seg is not None
        for _attempt in range(4):
            t_plan = time.perf_counter_ns()
            q_s, v_s, status_ns = await self.engine.joints_now(track)
            k = branch_point(seg, self.link.now() + self.link.rtt_ns + self.engine.plan_ns + SWITCH_MARGIN_NS)
            if k is None:
                return None
            t_b = seg.t_ns(k)
            loop = self.book.loop(track)
            (q_pred, v_pred, held), _ = predict_state(seg, loop, (q_s, v_s, status_ns), t_b)
            motion = plan(q_pred, v_pred)
            tick0 = self.book.phase_at(seg, t_b)
            sections = self.book.cut(track, motion, self.engine.rate_hz, v_pred, tick0, held)
            ids = track.take_ids(len(sections) + 1)
            new = Segment(t_b, motion, sections, ids, tick0 if seg.tick0 is not None else None, seg.robot)
            took = time.perf_counter_ns() - t_plan
            self.engine.plan_ns = max(took, int(0.7 * self.engine.plan_ns + 0.3 * took))
            # the switch goes in while the old motion still streams; it counts only if it is in place
            # before the robot leaves the branching TP, which the data plane's clock in the reply tells
            first = tp_batch(track, new, 0, min(self.engine.episode, len(ids)))
            branch = seg.ids[k]
            reply = await self.engine.apply(track, first, [], [(track.robot, branch, ids[0])])
            if reply.now_ns < t_b - SWITCH_MARGIN_NS // 2:
                break
            # in place late: once the branch's time has passed, the data plane says which way it went
            await self.link.sleep_until(t_b + SWITCH_MARGIN_NS // 2)
            st = await self.link.state(track.robots)
            if any(r.tp_id in ids for r in st.robots if r.robot_id == track.robot):
                break  # it took the branch after all
            await self.engine.apply(track, None, ids[: self.engine.episode], [(track.robot, branch, None)])
            self.engine.plan_ns *= 2  # too slow this time: branch further ahead
        else:
            raise PlanError("could not branch off in time (the link or the planning is too slow)")
        await self.stopping.halt(track)
        self.engine.last_switch = Switch(branch, t_b, (t_b - reply.now_ns) / 1e6, q_pred, v_pred)
        track.segment = new
        self.engine.stream(track, new)
        self.stopping.publish_plan(track, new)
        return MotionResult(t_b, new.end_ns, sections.q[-1].copy())

    # --- stops over the Responsive Link, and the watch on the data plane ---------------------------

    async def stopped_on_link(self, robot: int) -> None:
        """A robot was stopped over the Responsive Link (the data plane has cleared its registers and
        ramps it down): stop streaming its motion (MotionStopped to whoever waits) and unload it."""
        self.book.stopped[robot] = time.monotonic()
        await self._let_go(robot, f"robot {robot} was stopped over the Responsive Link")

    def released_on_link(self, robot: int) -> None:
        self.book.stopped.pop(robot, None)

    async def held_by_program(self, robot: int, text: str) -> None:
        """A URScript program sent to the robot's UR interfaces holds it (cell.ur): the data plane's
        commands are ignored there, so its motion ends (MotionStopped, with why) and no other starts
        until the program ends."""
        self.book.programs[robot] = text
        await self._let_go(robot, f"robot {robot}: {text}")

    def program_ended(self, robot: int) -> None:
        self.book.programs.pop(robot, None)

    async def _let_go(self, robot: int, reason: str) -> None:
        track = self.book.track(robot)
        track.stop_reason = reason
        track.epoch += 1
        await self.stopping.halt(track)
        if track.loaded:
            with contextlib.suppress(RemoteError):
                await self.engine.apply(track, None, list(track.loaded))
        track.segment, track.q_hold = None, None  # the next motion starts where the robot stands

    async def supervise(self) -> None:
        """Watch the data plane for as long as the controller runs (cell.controller.supervision)."""
        await supervision.supervise(self)

    async def take_over(self, plan_stops: bool = True) -> None:
        await supervision.take_over(self, plan_stops)

    # --- prepared ahead (cell.controller.prepared) ------------------------------------------------

    async def arm(self, goals: dict[int | str, np.ndarray], speed: float = 1.0) -> Armed:
        """Load robots' joint motions behind holds, to be started together by fire()."""
        return await prepared.arm(self, goals, speed)

    async def fire(self, armed: Armed, wait: bool = True) -> MotionResult:
        """Start armed motions with one update of switch entries."""
        return await prepared.fire(self, armed, wait)

    async def run_loop(
        self, robot: int | str, waypoints: list[np.ndarray], speed: float = 1.0, laps: int = 0
    ) -> LoopRun:
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
