"""Responsive Link packets, sans IO: fixed-size event (16 bytes) and data (64 bytes) packets.

As in the paper's Fig. 4 each packet is a 4-byte header, a payload (8 bytes
for an event, 56 for data) and a 4-byte trailer; the byte-by-byte layout is
docs/protocols/rlink.md.  The size says the kind, and the header says it again,
so that a packet on the wrong link is caught.  decode() raises nothing but
PacketError, whose `reason` is the drop counter it goes to.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum

HEADER = 4
TRAILER = 4
EVENT_PAYLOAD = 8
DATA_PAYLOAD = 56
EVENT_SIZE = HEADER + EVENT_PAYLOAD + TRAILER  # 16
DATA_SIZE = HEADER + DATA_PAYLOAD + TRAILER  # 64
MAX_HOPS = 16  # a packet's hop budget when it is made; a node drops one that has none left
PRIORITIES = 4  # 2 bits (the paper's P0, P1); 3 is the most urgent
TYPES = 32  # 5 bits


class Kind(IntEnum):
    EVENT = 0
    DATA = 1


SIZE = {Kind.EVENT: EVENT_SIZE, Kind.DATA: DATA_SIZE}
PAYLOAD = {Kind.EVENT: EVENT_PAYLOAD, Kind.DATA: DATA_PAYLOAD}


class EventType(IntEnum):
    """What an event packet says (state transitions and beacons, as in the paper's Sec. 2.2)."""

    NOP = 0
    ESTOP = 1  # emergency stop
    STOP = 2
    START = 3
    RESUME = 4
    MODE = 5  # change of control state
    BEACON = 6  # periodic: clock and liveness (a watchdog notices its absence)
    STATE = 7  # a node's report of its state (e.g. "standing still")
    ECHO = 8  # answered with ECHO_REPLY, the same payload (round-trip measurements)
    ECHO_REPLY = 9


class Drop(StrEnum):
    """Why a node dropped a packet: the counter it goes to (Node.drops)."""

    TRUNCATED = "truncated"
    OVERSIZED = "oversized"
    CRC = "crc"
    KIND = "kind"
    LENGTH = "length"
    FEC = "fec"  # more bit errors than the FEC line corrects
    NO_ROUTE = "no_route"
    HOPS = "hops"  # its hop count ran out


class PacketError(ValueError):
    """A packet that is dropped; `reason` names the counter it goes to."""

    def __init__(self, reason: Drop, text: str) -> None:
        self.reason = reason
        super().__init__(f"{reason}: {text}")


# --- CRC-16/CCITT-FALSE: x^16 + x^12 + x^5 + 1, init 0xFFFF, MSB first, no final XOR ----------------


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021 if crc & 0x8000 else crc << 1) & 0xFFFF
        table.append(crc)
    return table


_CRC = _crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ _CRC[(crc >> 8) ^ b]
    return crc


# --- packets --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Packet:
    kind: Kind
    dst: int  # node address 0..255
    src: int
    priority: int  # 0..3, 3 the most urgent
    type: int  # 0..31 (EventType for events)
    seq: int  # 0..255, per source and kind: losses show as gaps
    payload: bytes = b""  # up to 8 (event) or 56 (data) bytes; the rest of the field is zeros
    hops: int = MAX_HOPS  # hops left

    def __post_init__(self) -> None:
        for name, value, top in (
            ("dst", self.dst, 255),
            ("src", self.src, 255),
            ("priority", self.priority, PRIORITIES - 1),
            ("type", self.type, TYPES - 1),
            ("seq", self.seq, 255),
            ("hops", self.hops, 255),
        ):
            if not 0 <= value <= top:
                raise ValueError(f"{name} must be 0..{top} (got {value})")
        if len(self.payload) > PAYLOAD[self.kind]:
            raise ValueError(f"a {self.kind.name.lower()} payload holds {PAYLOAD[self.kind]} bytes at most")


def encode(p: Packet) -> bytes:
    """The packet's bytes: header, payload padded with zeros, trailer with the CRC."""
    head = bytes((p.dst, p.src, p.priority << 6 | p.kind << 5 | p.type, p.seq))
    body = head + p.payload.ljust(PAYLOAD[p.kind], b"\0") + bytes((p.hops, len(p.payload)))
    return body + crc16(body).to_bytes(2, "big")


def decode(raw: bytes | bytearray | memoryview, kind: Kind | None = None) -> Packet:
    """A packet from its bytes, checked; `kind`: the link it came on (None: either)."""
    raw = bytes(raw)
    n = len(raw)
    if n not in (EVENT_SIZE, DATA_SIZE):  # (a whole packet of the other kind is a "kind" drop below)
        want = [SIZE[kind]] if kind is not None else [EVENT_SIZE, DATA_SIZE]
        short = n < want[0] or (len(want) == 2 and want[0] < n < want[1])
        sizes = " or ".join(map(str, want))
        raise PacketError(Drop.TRUNCATED if short else Drop.OVERSIZED, f"{n} bytes: packets here are {sizes}")
    if crc16(raw[:-2]) != int.from_bytes(raw[-2:], "big"):
        raise PacketError(Drop.CRC, "the trailer's CRC does not match")
    said = Kind(raw[2] >> 5 & 1)
    if SIZE[said] != n:
        raise PacketError(Drop.KIND, f"a {n}-byte packet whose header says {said.name.lower()}")
    if kind is not None and said != kind:
        raise PacketError(Drop.KIND, f"a {said.name.lower()} packet on the {kind.name.lower()} link")
    used = raw[-3]
    if used > PAYLOAD[said]:
        raise PacketError(Drop.LENGTH, f"payload length {used} > {PAYLOAD[said]}")
    return Packet(
        kind=said,
        dst=raw[0],
        src=raw[1],
        priority=raw[2] >> 6,
        type=raw[2] & 0x1F,
        seq=raw[3],
        payload=raw[HEADER : HEADER + used],
        hops=raw[-4],
    )
