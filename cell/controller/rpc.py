"""The controller's requests as the bus carries them (ControllerService): each method checks its
request, calls the Controller and turns its outcomes into replies or RpcFaults with the codes users
see (unknown_robot, bad_request, unreachable, plan, stopped, busy, timeout).  services/controller.py
serves it on the bus.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np

from cell.bus import BusError, FaultCode, RemoteError, RpcFault
from cell.controller.controller import Controller, MotionResult, MotionStopped, Track
from cell.controller.motion import FollowResult, NotAtGoal
from cell.controller.plan import PlanError
from cell.counters import Counters
from cell.robot.kinematics import Unreachable
from cell.robot.pose import from_adept, to_adept
from cell.skills.protocol import NAME  # (a named trajectory's name travels in skill commands)
from cell.trajectory.model import Trajectory, TrajectoryError
from cell.trajectory.wire import from_message
from cell.v1 import controller_pb2

Kind, Frame = controller_pb2.MoveRequest.Kind, controller_pb2.MoveRequest.Frame


@dataclass(slots=True)
class ControllerCounters(Counters):
    alternates_taken: int = 0  # armed alternates taken on an event from the bus
    alternates_refused: int = 0
    late_starts: int = 0  # motions whose first point was due before it reached the data plane
    start_shifts: int = 0  # starts moved on by whole windows: their update waited for another's
    late_stops: int = 0  # stops in place after the command window they were planned from began
    not_at_goal: int = 0  # motions that ran to their end with the robot read elsewhere (failed)
    stopped_on_link: int = 0  # robots stopped over the Responsive Link now (a gauge)
    motions_lost: int = 0  # robots whose motion was lost with the data plane (a gauge)
    stale_link_events: int = 0  # stops and releases older than the robot's last one heard: ignored


class ControllerService:
    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        self.counters = ControllerCounters()

    def report(self) -> dict[str, float]:
        """The counters for the heartbeat, the controller's gauges read now."""
        c, ctl = self.counters, self.ctl
        c.late_starts, c.late_stops, c.not_at_goal, c.stopped_on_link, c.motions_lost = (
            ctl.engine.late_starts,
            ctl.stopping.late_stops,
            ctl.engine.not_at_goal,
            len(ctl.book.stopped),
            len(ctl.stopping.lost),
        )
        c.start_shifts = ctl.engine.start_shifts
        return c.as_dict()

    def _robot(self, name: str) -> int:
        try:
            return self.ctl.config.robot(name).id
        except KeyError:
            raise RpcFault(FaultCode.UNKNOWN_ROBOT, f"no robot named {name!r}") from None

    def _reply(self, robot: int, result: MotionResult) -> controller_pb2.MoveReply:
        pos, rot = self.ctl.pose_of(robot, result.q_end)
        return controller_pb2.MoveReply(
            t_start_ns=result.start_ns,
            t_end_ns=result.end_ns,
            joints=result.q_end.tolist(),
            pose=to_adept(pos, rot),
            t0_ns=result.t0_ns if isinstance(result, FollowResult) else 0,
            tps_per_s=result.tps_per_s if isinstance(result, FollowResult) else 0.0,
            fitted_deviation_mm=result.deviation_mm if isinstance(result, FollowResult) else 0.0,
        )

    async def _guard(self, robot: int, coro) -> controller_pb2.MoveReply:
        """The motion's reply (its end pose is the first robot's of a shared start), or its fault."""
        try:
            result = await coro
        except Unreachable as exc:
            raise RpcFault(FaultCode.UNREACHABLE, exc.reason) from None
        except PlanError as exc:
            raise RpcFault(FaultCode.PLAN, str(exc)) from None
        except MotionStopped as exc:
            raise RpcFault(FaultCode.STOPPED, str(exc)) from None
        except NotAtGoal as exc:
            raise RpcFault(FaultCode.FAILED, str(exc)) from None
        except RemoteError as exc:
            raise _refused(exc) from None
        except BusError as exc:
            raise RpcFault(FaultCode.STOPPED, f"the data plane is not answering: {exc}") from None
        return controller_pb2.MoveReply() if result is None else self._reply(robot, result)

    async def move(self, req: controller_pb2.MoveRequest) -> controller_pb2.MoveReply:
        rid = self._robot(req.robot)
        speed = _speed(req.speed)
        values = np.array(req.values, np.float64)
        ctl = self.ctl
        wait = not req.start_only
        track = ctl.track(rid)
        if req.kind == Kind.JOINTS:
            values = _joints(req, track)
            if req.frame != Frame.ABSOLUTE:
                values = values + await self._start(track)
            return await self._guard(rid, ctl.move_joints(rid, values, speed, req.fine, wait))
        try:
            d_pos, d_rot = from_adept(values)
        except ValueError as exc:
            raise RpcFault(FaultCode.BAD_REQUEST, str(exc)) from None
        pos, rot = d_pos, d_rot
        if req.frame != Frame.ABSOLUTE:
            here_pos, here_rot = ctl.pose_of(rid, await self._start(track))
            if req.frame == Frame.WORLD:
                pos, rot = here_pos + d_pos, d_rot @ here_rot
            else:
                pos, rot = here_pos + here_rot @ d_pos, here_rot @ d_rot
        if req.kind == Kind.LINEAR:
            return await self._guard(rid, ctl.move_linear(rid, pos, rot, speed, req.fine, wait))
        return await self._guard(rid, ctl.move_to(rid, pos, rot, speed, req.fine, wait))

    def _trajectories(self, msgs) -> dict[int | str, Trajectory]:
        """The messages as Trajectories by robot (bad_request for one that cannot be a trajectory)."""
        if not msgs:
            raise RpcFault(FaultCode.BAD_REQUEST, "no trajectories")
        trajs: dict[int | str, Trajectory] = {}
        for m in msgs:
            rid = self._robot(m.robot)
            if rid in trajs:
                raise RpcFault(FaultCode.BAD_REQUEST, f"two trajectories for robot {m.robot!r}")
            try:
                trajs[rid] = from_message(m, self.ctl.book.arm_of(rid).joints)
            except TrajectoryError as exc:
                raise RpcFault(FaultCode.BAD_REQUEST, f"trajectory of {m.robot}: {exc}") from None
        return trajs

    async def follow(self, req: controller_pb2.FollowRequest) -> controller_pb2.MoveReply:
        """Trajectories planned elsewhere, given or named: each checked and refused with its first
        offending point (bad_request for one that cannot be a trajectory, plan for one beyond the
        robot's limits or a name not known)."""
        if req.name:
            robots: list[int | str] = [self._robot(r) for r in req.robots]
            try:
                trajs = self.ctl.named_trajectories(req.name, robots)
            except PlanError as exc:
                raise RpcFault(FaultCode.PLAN, str(exc)) from None
        else:
            trajs = self._trajectories(req.trajectories)
        first = int(next(iter(trajs)))
        speed = _speed(req.speed or 50.0)
        run = self.ctl.follow(trajs, speed, wait=not req.start_only, replace=req.replace)
        return await self._guard(first, run)

    async def name(self, req: controller_pb2.NameRequest) -> controller_pb2.NameReply:
        """Keep trajectories under a name, checked now (plan: beyond a limit, or no room left)."""
        if not NAME.fullmatch(req.name):
            raise RpcFault(
                "bad_request", f"a trajectory's name is 1-64 of A-Z a-z 0-9 _ . - (got {req.name[:80]!r})"
            )
        trajs = self._trajectories(req.trajectories)
        try:
            self.ctl.name_trajectories(req.name, trajs)
        except PlanError as exc:
            raise RpcFault(FaultCode.PLAN, str(exc)) from None
        return controller_pb2.NameReply(
            name=req.name,
            robots=[next(c.name for c in self.ctl.config.robots if c.id == r) for r in trajs],
            points=sum(t.points for t in trajs.values()),
            duration_s=max(t.duration for t in trajs.values()),
        )

    async def move_together(self, req: controller_pb2.MoveTogetherRequest) -> controller_pb2.MoveReply:
        if not req.moves:
            raise RpcFault(FaultCode.BAD_REQUEST, "no moves")
        goals: dict[int | str, np.ndarray] = {}
        for m in req.moves:
            rid = self._robot(m.robot)
            track = self.ctl.track(rid)
            values = _joints(m, track)
            goals[rid] = values + await self._start(track) if m.frame != Frame.ABSOLUTE else values
        first = self._robot(req.moves[0].robot)
        return await self._guard(first, self.ctl.move_together(goals, _speed(req.moves[0].speed)))

    async def replan(self, req: controller_pb2.MoveRequest) -> controller_pb2.MoveReply:
        """Switch a moving robot onto a new joint motion on the fly (TrajectorySwitcher); replies
        when the new motion has ended."""
        rid = self._robot(req.robot)
        values = _joints(req, self.ctl.track(rid))
        return await self._guard(rid, self.ctl.replan(rid, values, _speed(req.speed)))

    async def _start(self, track: Track) -> np.ndarray:
        try:
            return await self.ctl.engine.start_q(track)
        except PlanError as exc:
            raise RpcFault(FaultCode.BUSY, str(exc)) from None

    async def stop(self, req: controller_pb2.StopRequest) -> controller_pb2.StopReply:
        names = list(req.robots) or [r.name for r in self.ctl.config.robots]
        ids = [self._robot(n) for n in names]
        results = await self.ctl.stop(ids)
        tracks = [self.ctl.track(i) for i in results]
        stopped = [r.name for r in self.ctl.config.robots if any(r.id in t.robots for t in tracks)]
        t_ns = max((r.start_ns for r in results.values()), default=0)
        return controller_pb2.StopReply(robots=stopped, t_ns=t_ns)

    async def resume(self, req: controller_pb2.RobotRequest) -> controller_pb2.MoveReply:
        rid = self._robot(req.robot)
        return await self._guard(rid, self.ctl.resume(rid))

    async def arrive(self, req: controller_pb2.ArriveRequest) -> controller_pb2.PoseReply:
        rid = self._robot(req.robot)
        try:
            q, t_ns = await self.ctl.arrive(rid, req.tolerance_rad or 2e-4, req.timeout_s or 60.0)
        except MotionStopped as exc:
            raise RpcFault(FaultCode.STOPPED, str(exc)) from None
        except NotAtGoal as exc:
            raise RpcFault(FaultCode.FAILED, str(exc)) from None
        except RemoteError as exc:
            raise _refused(exc) from None
        except BusError as exc:  # (a BusTimeout is a TimeoutError too: not the robot's)
            raise RpcFault(FaultCode.STOPPED, f"the data plane is not answering: {exc}") from None
        except TimeoutError:
            raise RpcFault(
                "timeout", f"robot {req.robot} did not arrive within {req.timeout_s or 60.0} s"
            ) from None
        pos, rot = self.ctl.pose_of(rid, q)
        return controller_pb2.PoseReply(joints=q.tolist(), pose=to_adept(pos, rot), t_ns=t_ns)

    async def pose(self, req: controller_pb2.RobotRequest) -> controller_pb2.PoseReply:
        rid = self._robot(req.robot)
        try:
            q, _, t_ns = await self.ctl.joints_now(self.ctl.track(rid))
        except PlanError as exc:
            raise RpcFault(FaultCode.UNKNOWN_ROBOT, str(exc)) from None
        pos, rot = self.ctl.pose_of(rid, q)
        return controller_pb2.PoseReply(joints=q.tolist(), pose=to_adept(pos, rot), t_ns=t_ns)

    # --- prepared ahead (cell.controller.prepared) --------------------------------------------

    def _goal(self, values, track: Track) -> np.ndarray:
        q = np.array(values, np.float64)
        if q.size != track.joints or not np.isfinite(q).all():
            raise RpcFault(
                FaultCode.BAD_REQUEST, f"a goal takes {track.joints} finite joint values, got {q.size}"
            )
        return q

    async def prepare_alternates(
        self, req: controller_pb2.AlternatesRequest
    ) -> controller_pb2.AlternatesReply:
        rid = self._robot(req.robot)
        track = self.ctl.track(rid)
        if not req.alternates or len({a.name for a in req.alternates}) != len(req.alternates):
            raise RpcFault(FaultCode.BAD_REQUEST, "alternates need distinct names, at least one")
        goals = {a.name: self._goal(a.values, track) for a in req.alternates}
        try:
            n = await self.ctl.prepare_alternates(rid, goals, _speed(req.speed), req.every or 1)
        except PlanError as exc:
            raise RpcFault(FaultCode.PLAN, str(exc)) from None
        except RemoteError as exc:  # the data plane refused them (a full table says why)
            raise RpcFault(exc.code, exc.message) from None
        _, branches = self.ctl.engine.alternates[rid]
        return controller_pb2.AlternatesReply(tps_loaded=n, branch_points=len(next(iter(branches.values()))))

    async def take_alternate(self, req: controller_pb2.TakeAlternate) -> controller_pb2.MoveReply:
        rid = self._robot(req.robot)
        return await self._guard(rid, self.ctl.take_alternate(rid, req.name))

    async def loop(self, req: controller_pb2.LoopRequest) -> controller_pb2.LoopReply:
        rid = self._robot(req.robot)
        track = self.ctl.track(rid)
        values = np.array(req.values, np.float64)
        if values.size == 0 or values.size % track.joints or not np.isfinite(values).all():
            raise RpcFault(FaultCode.BAD_REQUEST, f"waypoints take {track.joints} finite joint values each")
        waypoints = list(values.reshape(-1, track.joints))
        try:
            run = await self.ctl.run_loop(rid, waypoints, _speed(req.speed), req.laps)
            laps = 0
            if not req.start_only:
                laps = await asyncio.shield(run.done)
                await self.ctl.wait_idle(rid)  # (back where it began)
                if isinstance(track.failure, NotAtGoal):
                    raise RpcFault(FaultCode.FAILED, str(track.failure))
        except PlanError as exc:
            raise RpcFault(FaultCode.PLAN, str(exc)) from None
        except MotionStopped as exc:
            raise RpcFault(FaultCode.STOPPED, str(exc)) from None
        return controller_pb2.LoopReply(t_start_ns=run.start_ns, lap_ns=run.lap_ns, laps=laps)

    async def end_loop(self, req: controller_pb2.RobotRequest) -> controller_pb2.LoopReply:
        rid = self._robot(req.robot)
        run = self.ctl.engine.loops.get(rid)
        try:
            laps = await self.ctl.end_loop(rid)
        except PlanError as exc:
            raise RpcFault(FaultCode.PLAN, str(exc)) from None
        assert run is not None
        return controller_pb2.LoopReply(t_start_ns=run.start_ns, lap_ns=run.lap_ns, laps=laps)


def _refused(exc: RemoteError) -> RpcFault:
    """The data plane's refusal of an update, passed on with its code and reason (taken, ...)."""
    code = FaultCode(exc.code) if exc.code in {c.value for c in FaultCode} else FaultCode.FAILED
    return RpcFault(code, f"the data plane refused: {exc.message}")


def _speed(percent: float) -> float:
    """A request's speed (percent, 0 meaning 100) as a factor; bad_request outside (0, 100]."""
    speed = (percent or 100.0) / 100.0
    if not 0.0 < speed <= 1.0:
        raise RpcFault(FaultCode.BAD_REQUEST, f"speed must be in (0, 100] %, got {percent}")
    return speed


def _joints(m: controller_pb2.MoveRequest, track: Track) -> np.ndarray:
    """A joint-space request's joint positions; bad_request unless one finite value per joint."""
    values = np.array(m.values, np.float64)
    if m.kind != Kind.JOINTS or values.size != track.joints or not np.isfinite(values).all():
        raise RpcFault(
            FaultCode.BAD_REQUEST, f"{m.robot}: {track.joints} finite joint positions (rad) expected"
        )
    return values
