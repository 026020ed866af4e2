"""One robot's AdeptServer-style skill server (RobotSkills): its connections, its command queue in
arrival order, and each skill's semantics as on the V+ controller (motions through the controller
service, `break`, `set_speed`, air, e-stop over the Responsive Link).  The protocol itself is the
sans-IO cell.skills.protocol; services/skills.py opens one TCP server per robot around this.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from google.protobuf.message import Message

from cell.bus import Bus, BusTimeout, RemoteError, ServiceDown
from cell.config import CellConfig, RobotConfig
from cell.counters import Counters
from cell.rlink.client import EventClient
from cell.robot.node import WAKE_HZ
from cell.robot.pose import to_adept
from cell.skills.protocol import (
    MOTIONS,
    NAMED_SKILLS,
    NO_ID,
    Command,
    CommandReader,
    Done,
    Error,
    ErrorCode,
    Reply,
)
from cell.v1 import controller_pb2, robot_pb2, skills_pb2

log = logging.getLogger("cell.skills")
M = controller_pb2.MoveRequest
_MOTION = {
    "move_to": (M.POSE, M.ABSOLUTE),
    "move_rel_world": (M.POSE, M.WORLD),
    "move_rel_tool": (M.POSE, M.TOOL),
    "move_joints": (M.JOINTS, M.ABSOLUTE),
    "move_rel_joints": (M.JOINTS, M.WORLD),
}
_CODES = {  # the controller's error codes -> the protocol's
    "unreachable": ErrorCode.UNREACHABLE,
    "plan": ErrorCode.UNREACHABLE,
    "stopped": ErrorCode.STOPPED,
    "bus_lost": ErrorCode.STOPPED,  # the controller stops what it can no longer see through
    "bad_request": ErrorCode.ARGUMENTS,
}


@dataclass(slots=True)
class ServerCounters(Counters):
    commands: int = 0
    errors: int = 0
    connections: int = 0
    held_pose_acks: int = 0  # acks that reported the broadcast pose (no bus round trip)
    asked_pose_acks: int = 0  # acks whose pose was asked of the controller (none held fresh enough)
    refused_connections: int = 0  # over max_connections(_per_peer)
    slow_lines: int = 0  # connections closed for a message not ended within line_timeout_s
    paused_reads: int = 0  # times a connection had max_pending unanswered and was not read
    open: int = 0  # connections open now (a gauge)


@dataclass
class Job:
    command: Command
    received_ns: int
    reply: asyncio.Future[Reply]
    started_ns: int = 0


class RobotSkills:
    """One robot's skill server: its connections, its command queue, its state (speed, air)."""

    def __init__(
        self, robot: RobotConfig, config: CellConfig, bus: Bus, t0_ns: int, link: EventClient | None = None
    ) -> None:
        self.robot, self.config, self.bus, self.t0_ns = robot, config, bus, t0_ns
        self.link = link
        self.queue: asyncio.Queue[Job] = asyncio.Queue()
        self.speed: float | None = None  # for the next motion only
        self.air = False
        self.counters = ServerCounters()
        self.open = 0  # connections open now
        self.per_peer: dict[str, int] = defaultdict(int)
        # the robot's last state broadcast (truth/<robot>): the tool pose a non-motion ack reports
        self.held: robot_pb2.RobotTruth | None = None  # (converted only when an ack needs it)
        # fresh: at most two of its deliveries old (a group ticking in C publishes its truths in bursts,
        # each WAKE_HZ wake-up, not one every truth period)
        self.held_max_age_ns = int(2e9 / min(robot.truth_hz, WAKE_HZ)) if robot.truth_hz else 0

    async def here(self) -> tuple[float, ...]:
        """The tool pose now: the held one if it is fresh (not older than two of its deliveries: at most
        one plus the bus), else the controller's, asked over the bus."""
        m = self.held
        if m is not None and time.monotonic_ns() - m.t_ns <= self.held_max_age_ns:
            self.counters.held_pose_acks += 1
            p = m.tool_pose  # x, y, z (m), qw, qx, qy, qz
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, np.array(p[3:7]))
            return to_adept(np.array(p[:3]), rot.reshape(3, 3))
        name = self.robot.name
        self.counters.asked_pose_acks += 1
        return tuple(
            (await self._ask("pose", controller_pb2.RobotRequest(robot=name), controller_pb2.PoseReply)).pose
        )

    def seconds(self, t_ns: int) -> float:
        return (t_ns - self.t0_ns) / 1e9

    def _refusal(self, ip: str) -> str | None:
        cfg = self.config.skills
        if self.open >= cfg.max_connections:
            return f"too many connections ({cfg.max_connections} open)"
        if self.per_peer[ip] >= cfg.max_connections_per_peer:
            return f"too many connections from {ip} ({cfg.max_connections_per_peer} open)"
        return None

    async def serve_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read commands, queue them, write replies in the order the commands came.  A peer gets at
        most [skills] max_connections(_per_peer) connections, max_pending unanswered commands each
        (then the server stops reading it: TCP pushes back) and line_timeout_s to finish a message."""
        peer = writer.get_extra_info("peername")
        ip = peer[0] if peer else "?"
        client = f"{ip}:{peer[1]}" if peer else "?"
        if (why := self._refusal(ip)) is not None:
            self.counters.refused_connections += 1
            with contextlib.suppress(ConnectionError, OSError):
                writer.write(Error(NO_ID, ErrorCode.BUSY, why).encode())
                writer.close()
            return
        self.open += 1
        self.counters.open = self.open
        self.per_peer[ip] += 1
        self.counters.connections += 1
        cfg = self.config.skills
        parser = CommandReader()
        pending: asyncio.Queue[tuple[asyncio.Future[Reply], Job | None]] = asyncio.Queue()
        slots = asyncio.Semaphore(cfg.max_pending)

        async def write_replies() -> None:
            while True:
                fut, job = await pending.get()
                reply = await fut
                slots.release()
                if job is not None:
                    self._trace(job, reply, client)
                try:
                    writer.write(reply.encode())
                    await writer.drain()
                except (ConnectionError, OSError):
                    return  # the client is gone: its commands still run, nobody reads the replies

        try:
            async with asyncio.TaskGroup() as tg:
                writing = tg.create_task(write_replies())
                line_began: float | None = None
                try:
                    while True:
                        if parser.partial:  # a message has begun: it has line_timeout_s to end
                            line_began = line_began if line_began is not None else time.monotonic()
                            left: float | None = line_began + cfg.line_timeout_s - time.monotonic()
                        else:
                            line_began, left = None, None
                        try:
                            async with asyncio.timeout(left):
                                data = await reader.read(65536)
                        except TimeoutError:
                            self.counters.slow_lines += 1
                            why = f"a command message must end within {cfg.line_timeout_s:g} s"
                            writer.write(Error(NO_ID, ErrorCode.BUSY, why).encode())
                            break
                        if not data:
                            break
                        now = time.monotonic_ns()
                        for item in parser.feed(data):
                            if slots.locked():  # max_pending unanswered: read no more until one is
                                self.counters.paused_reads += 1
                            await slots.acquire()
                            fut: asyncio.Future[Reply] = asyncio.get_running_loop().create_future()
                            if isinstance(item, Error):
                                self.counters.errors += 1
                                fut.set_result(item)
                                pending.put_nowait((fut, None))
                                continue
                            job = Job(item, now, fut)
                            pending.put_nowait((fut, job))
                            if item.skill in NAMED_SKILLS:  # out of turn: never behind the queue
                                tg.create_task(self.run_job(job, self.link_order))
                            else:
                                self.queue.put_nowait(job)
                    # the client closed: its commands still run (a motion once sent is not taken
                    # back), their replies are not written
                except (ConnectionError, OSError):
                    pass
                finally:
                    writing.cancel()
                    writer.close()
                    with contextlib.suppress(Exception):
                        await writer.wait_closed()
        finally:
            self.open -= 1
            self.counters.open = self.open
            self.per_peer[ip] -= 1
            if not self.per_peer[ip]:
                del self.per_peer[ip]  # (peers come and go: the table holds only those connected)

    def _trace(self, job: Job, reply: Reply, client: str) -> None:
        started = job.started_ns or job.received_ns
        trace = skills_pb2.SkillTrace(
            robot=self.robot.name,
            id=job.command.id,
            skill=job.command.skill,
            received_ns=job.received_ns,
            started_ns=started,
            answered_ns=time.monotonic_ns(),
            status="done" if isinstance(reply, Done) else "error",
            code=reply.code if isinstance(reply, Error) else "",
            client=client,
        )
        self.bus.publish(f"skills/{self.robot.name}/trace", trace)

    async def run_queue(self) -> None:
        """Execute the robot's commands one at a time, in arrival order."""
        while True:
            await self.run_job(await self.queue.get(), self.execute)

    async def run_job(self, job: Job, execute: Any) -> None:
        """One command, answered whatever happens."""
        started = time.monotonic_ns()
        job.started_ns = started
        try:
            async with asyncio.timeout(self.config.skills.motion_timeout_s):
                reply = await execute(job.command, started)
        except (RemoteError, BusTimeout) as exc:  # (first: a BusTimeout is a TimeoutError too)
            reply = self._error(job.command.id, exc)
        except TimeoutError:
            reply = Error(job.command.id, ErrorCode.FAILED, "timed out")
        except Exception as exc:  # a bug must not take the server down: answer, log, go on
            log.exception("%s: %s failed", self.robot.name, job.command)
            reply = Error(job.command.id, ErrorCode.FAILED, f"{type(exc).__name__}: {exc}")
        self.counters.commands += 1
        if isinstance(reply, Error):
            self.counters.errors += 1
        if not job.reply.done():
            job.reply.set_result(reply)

    async def link_order(self, cmd: Command, started_ns: int) -> Reply:
        """estop / resume over the Responsive Link; done once every named robot has reported."""
        if self.link is None:
            return Error(cmd.id, ErrorCode.FAILED, "no Responsive Link in this server")
        if "all" in cmd.names:
            robots = None
        else:
            robots = list(cmd.names) or [self.robot.name]
            unknown = [n for n in robots if n not in {r.name for r in self.config.robots}]
            if unknown:
                return Error(cmd.id, ErrorCode.ARGUMENTS, f"no robot {unknown[0]!r} in this cell")
        order = self.link.estop if cmd.skill == "estop" else self.link.resume
        try:
            await order(robots)
        except TimeoutError as exc:
            return Error(cmd.id, ErrorCode.FAILED, str(exc))
        return self._done(cmd, started_ns, await self.here())

    def _error(self, cid: str, exc: Exception) -> Error:
        if isinstance(exc, ServiceDown):  # (its motions end where the new controller stops them)
            return Error(cid, ErrorCode.STOPPED, f"the controller failed ({exc.why}); motion stopped")
        if isinstance(exc, RemoteError):
            return Error(cid, _CODES.get(exc.code, ErrorCode.FAILED), exc.message)
        return Error(cid, ErrorCode.FAILED, "the controller did not answer in time")

    async def execute(self, cmd: Command, started_ns: int) -> Reply:
        name = self.robot.name
        if cmd.skill in MOTIONS:
            kind, frame = _MOTION[cmd.skill]
            values = list(cmd.args)
            if kind == M.JOINTS:
                values = [math.radians(v) for v in values]
            speed, self.speed = self.speed or 100.0, None
            req = M(robot=name, kind=kind, frame=frame, values=values, speed=speed, start_only=True)
            moved = await self._ask("move", req, controller_pb2.MoveReply)
            return self._done(cmd, started_ns, moved.pose)
        if cmd.skill == "follow":  # the trajectory named so, this robot's part; answered once started
            speed, self.speed = self.speed or 100.0, None
            req = controller_pb2.FollowRequest(name=cmd.names[0], robots=[name], speed=speed, start_only=True)
            followed = await self._ask("follow", req, controller_pb2.MoveReply)
            return self._done(cmd, started_ns, followed.pose)
        if cmd.skill == "break":
            tolerance = self.config.skills.break_tolerance_rad
            req = controller_pb2.ArriveRequest(robot=name, tolerance_rad=tolerance, timeout_s=self._timeout())
            arrived = await self._ask("arrive", req, controller_pb2.PoseReply)
            return self._done(cmd, started_ns, arrived.pose)
        if cmd.skill == "set_speed":
            self.speed = cmd.args[0]
        elif cmd.skill in ("enable_air", "disable_air"):
            self.air = cmd.skill == "enable_air"
            state = skills_pb2.AirState(robot=name, on=self.air, t_ns=time.monotonic_ns())
            self.bus.publish(f"skills/{name}/air", state)
        return self._done(cmd, started_ns, await self.here())

    def _timeout(self) -> float:
        return self.config.skills.motion_timeout_s

    async def _ask(self, method: str, req: Message, reply_type: type[Message]) -> Any:
        """A request to the controller service (it answers `arrive` when the robot is there)."""
        return await self.bus.request("controller", method, req, reply_type, self._timeout() + 1.0)

    def _done(self, cmd: Command, started_ns: int, pose: Sequence[float]) -> Done:
        p = tuple(float(v) for v in pose)
        assert len(p) == 6
        return Done(cmd.id, self.seconds(started_ns), self.seconds(time.monotonic_ns()), p)
