"""The skill servers' ASCII protocol (AdeptServer style), sans IO: bytes in, events out.

A command message is ``<id>:<skill>[:<args>]\\r\\n``: an 8-character id (pyadept
uses the first 8 hex digits of a uuid4), the skill's name, and its arguments
separated by commas.  Each command gets exactly one reply:

- ``<id>:done:<t_start>,<t_end>:<x>,<y>,<z>,<yaw>,<pitch>,<roll>\\r\\n``
  (seconds since the server started, 3 decimals; the tool pose in mm and
  degrees, 3 decimals: a motion's end for a motion, the measured pose on
  arrival for ``break``, and for ``set_speed`` and the air skills the latest
  pose the server holds from the robot's state broadcast, at most one
  broadcast period old plus the bus's delivery);
- ``<id>:error:<code>:<text>\\r\\n`` (new: the published AdeptServer answers
  nothing and the client hangs); ``00000000`` is the id when none can be read.

TCP delivers a byte stream: several messages may come in one segment and one
message in several, so ``CommandReader`` buffers; a line longer than
MAX_LINE is refused (and skipped up to its end) rather than buffered forever.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from cell.lines import LineReader, TooLong

MAX_LINE = 1024  # bytes of one command message, \r\n excluded
NO_ID = "00000000"
_ID = re.compile(r"[A-Za-z0-9_-]{8}")
_CODE = re.compile(r"[a-z_]+")

# skill -> number of real arguments
POSE_SKILLS = ("move_to", "move_rel_world", "move_rel_tool")  # x, y, z mm, yaw, pitch, roll deg
JOINT_SKILLS = ("move_joints", "move_rel_joints")  # 6 joint values, deg
SKILLS: dict[str, int] = {
    **{s: 6 for s in POSE_SKILLS + JOINT_SKILLS},
    "break": 0,
    "enable_air": 0,
    "disable_air": 0,
    "set_speed": 1,
}
MOTIONS = POSE_SKILLS + JOINT_SKILLS
# skills that name robots rather than take numbers: none = the server's own robot, "all" = every robot
# (new: the cell's e-stop and release over the Responsive Link; answered out of turn, at once)
NAMED_SKILLS = ("estop", "resume")
# a name a command carries: a robot's, or one the cell was given (a named trajectory's)
NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")
# skills that take one name of something the cell was given (new: follow:<name> runs the trajectory
# named so, cell/trajectory/, for this server's robot; queued as motions are)
NAME_SKILLS = ("follow",)


class ErrorCode:
    """The codes of error replies."""

    MALFORMED = "malformed"  # no id, or not <id>:<skill>[:<args>]
    UNKNOWN_SKILL = "unknown_skill"
    ARGUMENTS = "arguments"  # wrong number or value of arguments
    LINE_TOO_LONG = "line_too_long"
    UNREACHABLE = "unreachable"
    STOPPED = "stopped"  # the robot was stopped (protective stop, e-stop) during or before the command
    BUSY = "busy"  # the server refuses this connection (too many, or a message too slow to come)
    FAILED = "failed"  # anything else the server could not do; the text says what


@dataclass(frozen=True)
class Command:
    id: str
    skill: str
    args: tuple[float, ...] = ()
    names: tuple[str, ...] = ()  # NAMED_SKILLS: robots; NAME_SKILLS: the one name

    def encode(self) -> bytes:
        if self.names:
            return f"{self.id}:{self.skill}:{','.join(self.names)}\r\n".encode()
        if not self.args:
            return f"{self.id}:{self.skill}\r\n".encode()
        text = ",".join(_num(a) for a in self.args)
        return f"{self.id}:{self.skill}:{text}\r\n".encode()


@dataclass(frozen=True)
class Done:
    id: str
    t_start: float  # s since the server started
    t_end: float
    pose: tuple[float, float, float, float, float, float]  # x, y, z mm, yaw, pitch, roll deg

    def encode(self) -> bytes:
        pose = ",".join(f"{v:.3f}" for v in self.pose)
        return f"{self.id}:done:{self.t_start:.3f},{self.t_end:.3f}:{pose}\r\n".encode()


@dataclass(frozen=True)
class Error:
    id: str
    code: str
    text: str

    def encode(self) -> bytes:
        text = self.text.replace("\r", " ").replace("\n", " ")
        return f"{self.id}:error:{self.code}:{text}\r\n".encode()


Reply = Done | Error


def _num(x: float) -> str:
    return f"{x:.3f}" if isinstance(x, float) else str(x)


def parse_command(line: bytes) -> Command | Error:
    """One command message without its \\r\\n: a Command, or the Error to reply with."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        return Error(NO_ID, ErrorCode.MALFORMED, "not ASCII")
    parts = text.split(":")
    if len(parts) < 2 or not _ID.fullmatch(parts[0]):
        why = f"expected <8-character id>:<skill>[:<args>], got {text[:60]!r}"
        return Error(NO_ID, ErrorCode.MALFORMED, why)
    cid, skill = parts[0], parts[1].strip()
    if len(parts) > 3:
        return Error(cid, ErrorCode.MALFORMED, "too many ':' fields")
    raw = [a.strip() for a in parts[2].split(",")] if len(parts) == 3 and parts[2].strip() else []
    if skill in NAMED_SKILLS:
        bad = [n for n in raw if not NAME.fullmatch(n)]
        if bad:
            return Error(cid, ErrorCode.ARGUMENTS, f"{skill} takes robot names or 'all', got {bad[0][:40]!r}")
        return Command(cid, skill, names=tuple(raw))
    if skill in NAME_SKILLS:
        if len(raw) != 1 or not NAME.fullmatch(raw[0]):
            got = ",".join(raw)[:40]
            return Error(
                cid, ErrorCode.ARGUMENTS, f"{skill} takes one name of 1-64 A-Z a-z 0-9 _ . -, got {got!r}"
            )
        return Command(cid, skill, names=(raw[0],))
    if skill not in SKILLS:
        known = ", ".join([*SKILLS, *NAME_SKILLS, *NAMED_SKILLS])
        return Error(cid, ErrorCode.UNKNOWN_SKILL, f"no skill {skill!r} (skills: {known})")
    want = SKILLS[skill]
    if len(raw) != want:
        return Error(cid, ErrorCode.ARGUMENTS, f"{skill} takes {want} arguments, got {len(raw)}")
    try:
        args = tuple(float(a) for a in raw)
    except ValueError:
        return Error(cid, ErrorCode.ARGUMENTS, f"{skill}: arguments must be numbers, got {parts[2]!r}")
    if not all(math.isfinite(a) for a in args):
        return Error(cid, ErrorCode.ARGUMENTS, f"{skill}: arguments must be finite")
    if skill == "set_speed" and not 0 < args[0] <= 100:
        return Error(cid, ErrorCode.ARGUMENTS, f"set_speed takes a percentage in (0, 100], got {raw[0]}")
    return Command(cid, skill, args)


def parse_reply(line: bytes) -> Reply:
    """One reply without its \\r\\n; ValueError if it is neither a done nor an error reply."""
    text = line.decode("ascii")
    cid, _, rest = text.partition(":")
    kind, _, rest = rest.partition(":")
    if kind == "done":
        times, _, pose = rest.partition(":")
        t = [float(v) for v in times.split(",")]
        p = [float(v) for v in pose.split(",")]
        if len(t) != 2 or len(p) != 6:
            raise ValueError(f"malformed done reply {text!r}")
        return Done(cid, t[0], t[1], (p[0], p[1], p[2], p[3], p[4], p[5]))
    if kind == "error":
        code, _, msg = rest.partition(":")
        if not _CODE.fullmatch(code):
            raise ValueError(f"malformed error reply {text!r}")
        return Error(cid, code, msg)
    raise ValueError(f"not a reply: {text!r}")


class CommandReader:
    """A server connection's input: commands, and the error replies for what is not one."""

    def __init__(self) -> None:
        self._lines = LineReader(MAX_LINE)

    @property
    def partial(self) -> bool:
        """Part of a command message has come, its end not yet."""
        return self._lines.partial

    def feed(self, data: bytes) -> list[Command | Error]:
        out: list[Command | Error] = []
        for line in self._lines.feed(data):
            if isinstance(line, TooLong):
                head = line.head.decode("ascii", "replace")
                cid = head[:8] if _ID.fullmatch(head[:8]) and head[8:9] == ":" else NO_ID
                why = f"a command message is at most {MAX_LINE} bytes"
                out.append(Error(cid, ErrorCode.LINE_TOO_LONG, why))
            elif line.strip():
                out.append(parse_command(line))
        return out


class ReplyReader:
    """A client connection's input: replies."""

    def __init__(self) -> None:
        self._lines = LineReader(max_line=4 * MAX_LINE)

    def feed(self, data: bytes) -> list[Reply]:
        out = []
        for line in self._lines.feed(data):
            if isinstance(line, TooLong):
                raise ValueError("reply line too long")
            out.append(parse_reply(line))
        return out
