"""What the cell's event packets say: the payloads of ESTOP, STOP, RESUME, STATE and BEACON, sans IO.

An event payload is 8 bytes at most, so robots are named as a set: a 16-bit
base id and a 32-bit mask (bit i: robot base + i), with a 16-bit token the
requester picks to match the reports to its request.  Robots whose ids span
more than 32 go in several packets; base 0xFFFF means every robot.  A robot's
report (STATE) says which robot, what it is doing now and why.  The layout is
in docs/protocols/rlink.md; bad payloads raise EventError (counted and
dropped by whoever decodes them).
"""

from __future__ import annotations

import struct
from collections.abc import Collection, Iterable
from dataclasses import dataclass
from enum import IntEnum

ALL = 0xFFFF  # base of "every robot"
MASK_BITS = 32
_SET = struct.Struct("!HHI")  # token, base, mask
_STATE = struct.Struct("!HBBI")  # robot, state, reason, detail (e.g. us since the order came)
_BEACON = struct.Struct("!Q")  # the hub's CLOCK_MONOTONIC ns


class EventError(ValueError):
    pass


class RobotState(IntEnum):
    """A robot's state as nodes report it (STATE events)."""

    RUNNING = 0  # taking commands
    STOPPING = 1  # stopped by an event, still moving: braking
    STILL = 2  # stopped and standing still
    RESUMED = 3  # running again after a stop


class Reason(IntEnum):
    """Why a robot stopped (or resumed)."""

    NONE = 0
    ESTOP = 1  # an emergency stop was ordered
    STOP = 2  # a (non-emergency) stop was ordered
    WATCHDOG = 3  # the hub's beacon was lost
    RESUME = 4  # a resume was ordered
    BEACON = 5  # the beacon came back


@dataclass(frozen=True)
class RobotSet:
    """Robots named in one event packet."""

    token: int
    base: int
    mask: int

    def __contains__(self, robot: int) -> bool:
        if self.base == ALL:
            return True
        return 0 <= robot - self.base < MASK_BITS and bool(self.mask >> (robot - self.base) & 1)

    def ids(self, known: Collection[int]) -> list[int]:
        """Which of the `known` robot ids the set names (a set: fast for fleets)."""
        if self.base == ALL:
            return sorted(known)
        named = (self.base + i for i in range(MASK_BITS) if self.mask >> i & 1)
        return [r for r in named if r in known]

    def encode(self) -> bytes:
        return _SET.pack(self.token, self.base, self.mask)


def robot_sets(robots: Iterable[int] | None, token: int) -> list[RobotSet]:
    """The fewest sets naming these robot ids (None: every robot)."""
    if robots is None:
        return [RobotSet(token, ALL, 0)]
    ids = sorted(set(robots))
    if not ids:
        raise EventError("no robots named")
    if ids[0] < 0 or ids[-1] >= ALL:
        raise EventError(f"robot ids are 0..{ALL - 1}")
    sets: list[RobotSet] = []
    base, mask = ids[0], 0
    for r in ids:
        if r - base >= MASK_BITS:
            sets.append(RobotSet(token, base, mask))
            base, mask = r, 0
        mask |= 1 << (r - base)
    sets.append(RobotSet(token, base, mask))
    return sets


def decode_set(payload: bytes) -> RobotSet:
    if len(payload) != _SET.size:
        raise EventError(f"a robot set is {_SET.size} bytes (got {len(payload)})")
    token, base, mask = _SET.unpack(payload)
    if base != ALL and mask == 0:
        raise EventError("a robot set that names no robot")
    return RobotSet(token, base, mask)


@dataclass(frozen=True)
class StateReport:
    robot: int
    state: RobotState
    reason: Reason
    detail: int = 0  # STILL: microseconds from the order's arrival to standing still

    def encode(self) -> bytes:
        return _STATE.pack(self.robot, self.state, self.reason, min(self.detail, 0xFFFFFFFF))


def decode_state(payload: bytes) -> StateReport:
    if len(payload) != _STATE.size:
        raise EventError(f"a state report is {_STATE.size} bytes (got {len(payload)})")
    robot, state, reason, detail = _STATE.unpack(payload)
    try:
        return StateReport(robot, RobotState(state), Reason(reason), detail)
    except ValueError as exc:
        raise EventError(str(exc)) from None


def encode_beacon(t_ns: int) -> bytes:
    return _BEACON.pack(t_ns)


def decode_beacon(payload: bytes) -> int:
    if len(payload) != _BEACON.size:
        raise EventError(f"a beacon is {_BEACON.size} bytes (got {len(payload)})")
    return int(_BEACON.unpack(payload)[0])
