"""The robot datagram: one joint's status or command in 24 bytes (docs/protocols/robot-datagram.md).

Sans-IO: pure encode/decode, scalar and numpy-batched, no sockets.  Values
travel as fixed-point integers because the data plane (like the P4 switch it
stands for) has no floating point.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

SIZE = 24
# robot_id u16, joint_id u8, kind u8, seq u32, velocity i64, position i64 (network order)
_STRUCT = struct.Struct("!HBBIqq")
# the published in-network prototype's scale: 1 unit ~ 9.4e-8 rad (or rad/s)
SCALE = (2**31 - 1) / (64 * math.pi)
_I64 = 2**63 - 1
MAX_VALUE = _I64 / SCALE  # the largest magnitude a field can carry (~8.6e11 rad)

DTYPE = np.dtype(
    [
        ("robot_id", ">u2"),
        ("joint_id", "u1"),
        ("kind", "u1"),
        ("seq", ">u4"),
        ("velocity", ">i8"),
        ("position", ">i8"),
    ]
)
assert DTYPE.itemsize == SIZE


class Kind(IntEnum):
    STATUS = 0  # robot -> controller: current velocity and position
    COMMAND = 1  # controller -> robot: velocity to set, position echoed


class Reject(IntEnum):
    """Why a datagram was not accepted; services count drops per reason."""

    LENGTH = 0
    KIND = 1
    ROBOT = 2
    JOINT = 3


class DatagramError(ValueError):
    def __init__(self, reason: Reject, detail: str) -> None:
        self.reason = reason
        super().__init__(f"{reason.name.lower()}: {detail}")


@dataclass(frozen=True, slots=True)
class Datagram:
    robot_id: int
    joint_id: int
    kind: Kind
    seq: int
    velocity: float  # rad/s
    position: float  # rad


def to_fixed(x: float) -> int:
    """rad or rad/s -> the wire's integer units (round to nearest)."""
    if not math.isfinite(x) or abs(x) > MAX_VALUE:
        raise ValueError(f"{x!r} cannot be carried in a robot datagram (finite, |x| <= {MAX_VALUE:.3g})")
    return round(x * SCALE)


def from_fixed(i: int) -> float:
    return i / SCALE


def encode(d: Datagram) -> bytes:
    return _STRUCT.pack(d.robot_id, d.joint_id, d.kind, d.seq, to_fixed(d.velocity), to_fixed(d.position))


def decode(
    data: bytes,
    *,
    kind: Kind | None = None,
    robot_id: int | None = None,
    joints: int | None = None,
) -> Datagram:
    """Parse one datagram, checking what the caller expects; DatagramError(reason) if it is not that."""
    if len(data) != SIZE:
        raise DatagramError(Reject.LENGTH, f"{len(data)} bytes, expected {SIZE}")
    rid, jid, k, seq, vel, pos = _STRUCT.unpack(data)
    if k > Kind.COMMAND or (kind is not None and k != kind):
        wanted = f", expected {kind.value}" if kind is not None else ""
        raise DatagramError(Reject.KIND, f"kind {k}{wanted}")
    if robot_id is not None and rid != robot_id:
        raise DatagramError(Reject.ROBOT, f"robot {rid}, expected {robot_id}")
    if joints is not None and jid >= joints:
        raise DatagramError(Reject.JOINT, f"joint {jid}, this robot has {joints}")
    return Datagram(rid, jid, Kind(k), seq, vel / SCALE, pos / SCALE)


# --- batches -----------------------------------------------------------------------------------


def empty(n: int) -> np.ndarray:
    return np.zeros(n, DTYPE)


def pack(out: np.ndarray, robot_id, joint_id, kind: int, seq, velocity, position) -> None:
    """Fill a DTYPE array in place from floats (rad, rad/s); arguments broadcast."""
    out["robot_id"] = robot_id
    out["joint_id"] = joint_id
    out["kind"] = kind
    out["seq"] = seq
    out["velocity"] = np.rint(np.asarray(velocity, np.float64) * SCALE)
    out["position"] = np.rint(np.asarray(position, np.float64) * SCALE)


def view(buf: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
    """The DTYPE records in a buffer of whole datagrams (no copy); ValueError if it is not whole."""
    raw = np.frombuffer(buf, np.uint8) if not isinstance(buf, np.ndarray) else buf.view(np.uint8).ravel()
    if raw.size % SIZE:
        raise ValueError(f"{raw.size} bytes is not a whole number of {SIZE}-byte datagrams")
    return raw.view(DTYPE)


def velocities(records: np.ndarray) -> np.ndarray:
    return records["velocity"].astype(np.float64) / SCALE


def positions(records: np.ndarray) -> np.ndarray:
    return records["position"].astype(np.float64) / SCALE
