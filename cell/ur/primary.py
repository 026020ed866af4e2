"""The primary and secondary client interfaces' messages (30001, 30002), sans IO.

A UR controller greets each client of these ports with its version message and tells them what
programs say and where they fail: text messages (textmsg, popup) and runtime exceptions (the line,
the column, the reason).  Each is a package: int32 length (header included), uint8 type; robot
messages (type 20) then carry uint64 timestamp (us), int8 source, int8 robot message type.  The
robot state package (type 16, 10 Hz) is cell.ur.robotstate's.
"""

from __future__ import annotations

import struct
from enum import IntEnum

ROBOT_MESSAGE = 20
SOURCE_CONTROLLER = -2


class RobotMessage(IntEnum):
    TEXT = 0
    VERSION = 3
    SAFETY_MODE = 5
    ERROR_CODE = 6
    KEY = 7
    RUNTIME_EXCEPTION = 10


def _robot_message(kind: RobotMessage, t_us: int, body: bytes) -> bytes:
    payload = struct.pack(">QbB", t_us, SOURCE_CONTROLLER, kind) + body
    return struct.pack(">iB", 5 + len(payload), ROBOT_MESSAGE) + payload


def version(t_us: int, major: int, minor: int, bugfix: int, build: int, date: str = "") -> bytes:
    name = b"URControl"
    body = struct.pack(">b", len(name)) + name + struct.pack(">BBii", major, minor, bugfix, build)
    return _robot_message(RobotMessage.VERSION, t_us, body + date.encode())


def text(t_us: int, message: str) -> bytes:
    return _robot_message(RobotMessage.TEXT, t_us, message.encode(errors="replace"))


class ReportLevel(IntEnum):
    DEBUG = 0
    INFO = 1
    WARNING = 2
    VIOLATION = 3
    FAULT = 4


def error_code(t_us: int, code: int, argument: int, level: ReportLevel, message: str) -> bytes:
    """The controller's own report (C<code>A<argument>): int32 code, int32 argument, int32 report
    level, uint32 data type, uint32 data, then the text."""
    body = struct.pack(">iiiII", code, argument, level, 0, 0) + message.encode(errors="replace")
    return _robot_message(RobotMessage.ERROR_CODE, t_us, body)


def safety_mode(t_us: int, mode: int, code: int = 0, argument: int = 0) -> bytes:
    """The safety mode, as a UR tells it when it changes: int32 code, int32 argument, uint8 the mode,
    uint32 report data type, uint32 report data."""
    return _robot_message(RobotMessage.SAFETY_MODE, t_us, struct.pack(">iiBII", code, argument, mode, 0, 0))


def key_message(t_us: int, title: str, message: str, code: int = 0, argument: int = 0) -> bytes:
    """A key message (a program started, stopped): int32 code, int32 argument, uint8 title length,
    the title, then the text."""
    name = title.encode(errors="replace")[:255]
    body = struct.pack(">iiB", code, argument, len(name)) + name + message.encode(errors="replace")
    return _robot_message(RobotMessage.KEY, t_us, body)


def runtime_exception(t_us: int, line: int, column: int, message: str) -> bytes:
    body = struct.pack(">ii", line, column) + message.encode(errors="replace")
    return _robot_message(RobotMessage.RUNTIME_EXCEPTION, t_us, body)


def split(buf: bytearray) -> list[tuple[int, bytes]]:
    """Whole packages off the front of buf (removed from it), as rtde.split: (type, body after the
    5-byte header).  (For clients and tests.)"""
    out = []
    while len(buf) >= 5:
        size, kind = struct.unpack_from(">iB", buf)
        if size < 5 or size > len(buf):
            break
        out.append((kind, bytes(buf[5:size])))
        del buf[:size]
    return out


def read_robot_message(body: bytes) -> tuple[RobotMessage, bytes]:
    _t, _source, kind = struct.unpack_from(">QbB", body)
    return RobotMessage(kind), body[10:]
