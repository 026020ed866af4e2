"""Robot clients for task scripts (the pyadept style: ``await robot.cmdexec(MoveTo(...))``).

Commands are immutable objects whose ``get_messages()`` give the command
messages they stand for; motions append a ``break`` unless built with
``brk=False``, so that ``cmdexec`` returns when the robot has arrived.

``RobotClient`` owns one TCP connection to a robot's skill server.  A reader
task matches every reply to its message by id, so the client can be shared
between coroutines; a message is sent once and never again (a connection
lost mid-command raises ``ConnectionLost``: whether the robot moved is for
the script to find out, not for the client to guess by re-sending).  An
error reply raises ``SkillError`` carrying it.  With a bus, every request's
send and receive times and the server's timestamps are published on
``run/<robot>/request`` (``RequestTrace``), for Gantt charts and the Adept
paper's timing figures.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

from cell.bus import Bus, RemoteError
from cell.skills.protocol import NO_ID, Command, Done, Error, ReplyReader
from cell.trajectory.wire import to_message
from cell.v1 import controller_pb2, skills_pb2

Message = tuple[str, tuple[float, ...] | tuple[str, ...]]  # (skill, arguments: numbers, or names)


# --- commands ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Motion:
    brk: bool = field(default=True, kw_only=True)  # append a break: return when the robot has arrived

    skill = ""

    def values(self) -> tuple[float, ...]:
        raise NotImplementedError

    def get_messages(self) -> list[Message]:
        out: list[Message] = [(self.skill, self.values())]
        return [*out, ("break", ())] if self.brk else out


@dataclass(frozen=True)
class _PoseMotion(_Motion):
    x: float = 0.0  # mm
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0  # deg (Z-Y-Z, as in V+)
    pitch: float = 0.0
    roll: float = 0.0

    def values(self) -> tuple[float, ...]:
        return (self.x, self.y, self.z, self.yaw, self.pitch, self.roll)


@dataclass(frozen=True)
class MoveTo(_PoseMotion):
    """To an absolute tool pose (mm, deg)."""

    skill = "move_to"


@dataclass(frozen=True)
class MoveRelWorld(_PoseMotion):
    """By a displacement and turn in the base frame."""

    skill = "move_rel_world"


@dataclass(frozen=True)
class MoveRelTool(_PoseMotion):
    """By a displacement and turn in the tool's own frame."""

    skill = "move_rel_tool"


@dataclass(frozen=True)
class MoveToolZ(_Motion):
    """Along the tool's own z axis (approach and depart), mm."""

    z: float = 0.0
    skill = "move_rel_tool"

    def values(self) -> tuple[float, ...]:
        return (0.0, 0.0, self.z, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class _JointMotion(_Motion):
    joints: tuple[float, ...] = ()  # 6 values, deg

    def __post_init__(self) -> None:
        if len(self.joints) != 6:
            raise ValueError(f"{type(self).__name__} takes 6 joint values (deg), got {len(self.joints)}")

    def values(self) -> tuple[float, ...]:
        return tuple(float(v) for v in self.joints)


@dataclass(frozen=True)
class MoveJoints(_JointMotion):
    skill = "move_joints"


@dataclass(frozen=True)
class MoveRelJoints(_JointMotion):
    skill = "move_rel_joints"


@dataclass(frozen=True)
class SetSpeed:
    """Speed of the next motion, percent (0, 100] (V+'s SPEED)."""

    percent: float

    def __post_init__(self) -> None:
        if not 0 < self.percent <= 100:
            raise ValueError(f"speed is a percentage in (0, 100], got {self.percent}")

    def get_messages(self) -> list[Message]:
        return [("set_speed", (self.percent,))]


@dataclass(frozen=True)
class Break:
    """Wait until the robot has arrived."""

    def get_messages(self) -> list[Message]:
        return [("break", ())]


@dataclass(frozen=True)
class EnableAir:
    def get_messages(self) -> list[Message]:
        return [("enable_air", ())]


@dataclass(frozen=True)
class DisableAir:
    def get_messages(self) -> list[Message]:
        return [("disable_air", ())]


@dataclass(frozen=True)
class Follow:
    """Run the trajectory the cell was given under `name` (its part for this robot; docs/trajectories.md),
    at the speed set for the approach to its first point; with brk, return when it has ended."""

    name: str
    brk: bool = field(default=True, kw_only=True)

    def get_messages(self) -> list[Message]:
        out: list[Message] = [("follow", (self.name,))]
        return [*out, ("break", ())] if self.brk else out


RobotCommand = _Motion | SetSpeed | Break | EnableAir | DisableAir | Follow


# --- replies and errors --------------------------------------------------------------------------


@dataclass(frozen=True)
class Ack:
    """One acknowledgement: the message's id and skill, the server's times (s since it started),
    the tool pose it reports (mm, deg), and when the client sent and got it (monotonic ns)."""

    id: str
    skill: str
    status: str
    t_start: float
    t_end: float
    pose: tuple[float, ...]
    sent_ns: int
    received_ns: int


class SkillError(Exception):
    """The skill server answered a message with an error."""

    def __init__(self, robot: str, skill: str, error: Error) -> None:
        self.robot, self.skill, self.id, self.code, self.text = robot, skill, error.id, error.code, error.text
        super().__init__(f"{robot}: {skill} ({error.id}) failed: {error.code}: {error.text}")


class ConnectionLost(ConnectionError):
    """The connection went while messages were unanswered; they are not sent again."""


# --- the client ----------------------------------------------------------------------------------


class RobotClient:
    def __init__(self, name: str, host: str, port: int, bus: Bus | None = None) -> None:
        self.name, self.host, self.port, self.bus = name, host, port, bus
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task | None = None
        self._waiting: dict[str, asyncio.Future[Done | Error]] = {}
        self._send_lock = asyncio.Lock()
        self._ids = itertools.count(int.from_bytes(os.urandom(3), "big") << 8)

    async def connect(self, timeout: float = 10.0, backoff: float = 0.05) -> RobotClient:
        """Connect, retrying with exponential backoff until `timeout` (the cell may be starting)."""
        delay = backoff
        async with asyncio.timeout(timeout):
            while True:
                try:
                    reader, self._writer = await asyncio.open_connection(self.host, self.port)
                    break
                except OSError:
                    await asyncio.sleep(delay)
                    delay = min(delay * 2, 1.0)
        self._reader_task = asyncio.create_task(self._read(reader), name=f"robot-client-{self.name}")
        return self

    async def close(self) -> None:
        if self._reader_task is not None:
            self._reader_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader_task
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(Exception):
                await self._writer.wait_closed()
        self._fail_all("the client closed the connection")

    async def __aenter__(self) -> RobotClient:
        return await self.connect()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _new_id(self) -> str:
        """8 hex digits, unique on this connection (pyadept uses a uuid4's first 8: they may clash)."""
        return f"{next(self._ids) & 0xFFFFFFFF:08x}"

    async def _read(self, reader: asyncio.StreamReader) -> None:
        parser = ReplyReader()
        try:
            while data := await reader.read(65536):
                for reply in parser.feed(data):
                    fut = self._waiting.pop(reply.id, None)
                    if fut is not None and not fut.done():
                        fut.set_result(reply)
        except (OSError, ValueError):
            pass
        self._fail_all("the connection to the skill server was lost")

    def _fail_all(self, why: str) -> None:
        for fut in self._waiting.values():
            if not fut.done():
                fut.set_exception(ConnectionLost(f"{self.name}: {why}"))
        self._waiting.clear()

    async def _send(self, messages: Sequence[Message]) -> list[tuple[Command, asyncio.Future, int]]:
        if self._writer is None or self._reader_task is None or self._reader_task.done():
            raise ConnectionLost(f"{self.name}: not connected")
        loop = asyncio.get_running_loop()
        sent = []
        writer = self._writer
        async with self._send_lock:  # one batch's messages go out together, nothing between them
            for skill, args in messages:
                named = bool(args) and isinstance(args[0], str)  # (all names, or all numbers)
                cmd = (
                    Command(self._new_id(), skill, names=cast(tuple[str, ...], args))
                    if named
                    else Command(self._new_id(), skill, cast(tuple[float, ...], args))
                )
                fut: asyncio.Future[Done | Error] = loop.create_future()
                self._waiting[cmd.id] = fut
                data = cmd.encode()
                t = time.monotonic_ns()  # each message's own send time: the gaps between them are real
                writer.write(data)
                sent.append((cmd, fut, t))
            await writer.drain()
        return sent

    async def _await(self, cmd: Command, fut: asyncio.Future, sent_ns: int, timeout: float | None) -> Ack:
        try:
            async with asyncio.timeout(timeout):
                reply = await fut
        except TimeoutError:
            self._waiting.pop(cmd.id, None)
            why = f"{self.name}: no reply to {cmd.skill} ({cmd.id}) within {timeout} s"
            raise TimeoutError(why) from None
        got = time.monotonic_ns()
        self._trace(cmd, reply, sent_ns, got)
        if isinstance(reply, Error):
            raise SkillError(self.name, cmd.skill, reply)
        return Ack(cmd.id, cmd.skill, "done", reply.t_start, reply.t_end, reply.pose, sent_ns, got)

    def _trace(self, cmd: Command, reply: Done | Error, sent_ns: int, received_ns: int) -> None:
        if self.bus is None:
            return
        trace = skills_pb2.RequestTrace(
            robot=self.name,
            id=cmd.id,
            skill=cmd.skill,
            sent_ns=sent_ns,
            received_ns=received_ns,
            status="done" if isinstance(reply, Done) else "error",
            code=reply.code if isinstance(reply, Error) else "",
            t_start=reply.t_start if isinstance(reply, Done) else 0.0,
            t_end=reply.t_end if isinstance(reply, Done) else 0.0,
        )
        self.bus.publish(f"run/{self.name}/request", trace)

    async def cmdexec(self, *cmds: RobotCommand, timeout: float | None = None) -> list[Ack]:
        """Send the commands' messages one by one, each after the last was acknowledged; every
        acknowledgement, in order.  SkillError on an error reply (the rest is not sent)."""
        acks = []
        for cmd in cmds:
            for message in cmd.get_messages():
                ((c, fut, t),) = await self._send([message])
                acks.append(await self._await(c, fut, t, timeout))
        return acks

    async def follow(
        self, trajectory, *, speed: float | None = None, name: str = "", timeout: float | None = None
    ) -> list[Ack]:
        """Run a trajectory planned elsewhere (cell.trajectory.model.Trajectory, this robot's joint
        order) in turn with this robot's other commands; return when it has ended.  It is given to the
        cell under `name` (default `<robot>.script`, replaced by the next call) over the bus, checked
        there (SkillError naming the first point beyond a limit), then run by follow:<name>."""
        if self.bus is None:
            raise RuntimeError(
                f"{self.name}: follow() needs the client's bus (the cell's task scripts have it)"
            )
        name = name or f"{self.name}.script"
        t = trajectory
        req = controller_pb2.NameRequest(
            name=name, trajectories=[to_message(self.name, t.t, t.q, t.qd, t.qdd, name=t.name)]
        )
        try:
            await self.bus.request("controller", "name", req, controller_pb2.NameReply, 30.0)
        except RemoteError as exc:  # (refused: beyond a limit, no room; the reason as an error reply says)
            raise SkillError(self.name, "follow", Error(NO_ID, exc.code, exc.message)) from None
        cmds: list[RobotCommand] = [SetSpeed(speed)] if speed is not None else []
        return await self.cmdexec(*cmds, Follow(name), timeout=timeout)

    async def cmdexec_joined(self, *cmds: RobotCommand, timeout: float | None = None) -> list[Ack]:
        """Send all the commands' messages at once (the server still runs them in order); every
        acknowledgement, in order.  SkillError for the first error reply, after all have come."""
        sent = await self._send([m for cmd in cmds for m in cmd.get_messages()])
        waits = (self._await(c, f, t, timeout) for c, f, t in sent)
        results = await asyncio.gather(*waits, return_exceptions=True)
        acks = []
        for r in results:
            if isinstance(r, BaseException):
                raise r
            acks.append(r)
        return acks
