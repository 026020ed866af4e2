"""What the two sides of the bilateral experiment say on the Responsive Link, sans IO.

Data link, every control period, each way: one SAMPLE data packet (40 of its
56 payload bytes), little-endian:

    offset size  field
    0      8     sent_ns   u64  CLOCK_MONOTONIC when it was sent (both sides share the clock here)
    8      4     tick      u32  the sender's control period, counted from the START time
    12     1     state     u8   the sender's State
    13     1     mode      u8   the sender's Mode
    14     2     (zero)
    16     8     x, z      2 x f32  tip position, m
    24     8     vx, vz    2 x f32  tip velocity, m/s
    32     8     fx, fz    2 x f32  force on the tip from outside, N

Event link: START (payload: u64 start time, CLOCK_MONOTONIC ns, period 0
begins then), STOP, RESUME, ESTOP (no payload), MODE (u8 Mode), and each
side's STATE report (u8 role, u8 State, u32 tick).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

SAMPLE_TYPE = 1  # the data packets' type field
_SAMPLE = struct.Struct("<QIBBxx6f")
_START = struct.Struct("<Q")
_STATE = struct.Struct("<BBI")
SAMPLE_SIZE = _SAMPLE.size  # 40


class WireError(ValueError):
    """A payload that does not decode; the packet is counted and dropped."""


class State(IntEnum):
    IDLE = 0  # holding still, waiting for START
    RUNNING = 1
    STOPPED = 2  # holding still where it stopped (STOP, or the peer's data went stale)
    ESTOPPED = 3  # braked where it was, everything from the peer ignored until RESUME


class Role(IntEnum):
    LOCAL = 0
    REMOTE = 1


@dataclass(frozen=True)
class Sample:
    sent_ns: int
    tick: int
    state: int
    mode: int
    x: np.ndarray  # (2,)
    v: np.ndarray
    f: np.ndarray


def encode_sample(s: Sample) -> bytes:
    return _SAMPLE.pack(s.sent_ns, s.tick, s.state, s.mode, *s.x, *s.v, *s.f)


def decode_sample(raw: bytes) -> Sample:
    if len(raw) != _SAMPLE.size:
        raise WireError(f"a sample is {_SAMPLE.size} bytes (got {len(raw)})")
    sent, tick, state, mode, *vals = _SAMPLE.unpack(raw)
    if state not in State._value2member_map_:
        raise WireError(f"unknown state {state}")
    a = np.array(vals, dtype=float)
    if not np.isfinite(a).all():
        raise WireError("a sample with a non-finite value")
    return Sample(sent, tick, state, mode, a[0:2], a[2:4], a[4:6])


def encode_start(start_ns: int) -> bytes:
    return _START.pack(start_ns)


def decode_start(raw: bytes) -> int:
    if len(raw) != _START.size:
        raise WireError(f"START carries an 8-byte time (got {len(raw)} bytes)")
    return _START.unpack(raw)[0]


def encode_state(role: Role, state: State, tick: int) -> bytes:
    return _STATE.pack(role, state, tick & 0xFFFFFFFF)


def decode_state(raw: bytes) -> tuple[Role, State, int]:
    if len(raw) != _STATE.size:
        raise WireError(f"a STATE report is {_STATE.size} bytes (got {len(raw)})")
    role, state, tick = _STATE.unpack(raw)
    try:
        return Role(role), State(state), tick
    except ValueError as exc:
        raise WireError(str(exc)) from None
