"""SnP packets (SpW-SnP-MR), sans IO: bytes <-> packet objects, CRCs checked and made.

One packet per UDP datagram (the SpaceWire end of packet is the datagram's
end); layout and field meanings in docs/protocols/snp-mrt.md.  Multi-byte
fields are big-endian.  decode() never raises anything but PacketError, whose
`reply` says what the handler should answer (or None: drop), so that no
packet can stop a service.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum

# --- the RMAP CRC-8 (ECSS-E-ST-50-52C): x^8 + x^2 + x + 1, init 0, bytes LSB first, no final XOR --------


def _crc_table() -> bytes:
    table = bytearray(256)
    for i in range(256):
        crc = i
        for _ in range(8):
            crc = (crc >> 1) ^ 0xE0 if crc & 1 else crc >> 1
        table[i] = crc
    return bytes(table)


CRC_TABLE = _crc_table()


def crc8(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    for b in bytes(data):
        crc = CRC_TABLE[crc ^ b]
    return crc


# --- identifiers ----------------------------------------------------------------------------------


class Pid(IntEnum):
    MRT = 0xF0  # time-bounded queries
    TSP = 0xF1  # time synchronisation
    PID_MANAGEMENT = 0xF2


class PacketType(IntEnum):
    TIME_BOUNDED_QUERY = 0x0001
    TIME_BOUNDED_QUERY_REPLY = 0x0002
    TIME_BOUNDED_QUERY_DENIAL = 0x0003
    TIME_BOUNDED_QUERY_CANCELLATION = 0x0004
    # SnP-TSP (protocol 0xF1): a two-way time exchange
    TIME_REQUEST = 0x0010
    TIME_RESPONSE = 0x0011
    # PID management (protocol 0xF2)
    PID_SUPPORTED_QUERY = 0x0020
    PID_SUPPORTED_REPLY = 0x0021
    PID_LIST_QUERY = 0x0022
    PID_LIST_REPLY = 0x0023
    # error replies
    UNKNOWN_PID_REPLY = 0x00F1
    UNKNOWN_PACKET_TYPE_REPLY = 0x00F2
    INVALID_DATA_CRC_REPLY = 0x00F3


class Denial(IntEnum):
    DEADLINE_CANNOT_BE_MET = 1
    UNKNOWN_OUTPUT_ITEM = 2
    UNKNOWN_INPUT_ITEM = 3
    CANCELLED = 4


class Quantity(IntEnum):
    POSITION = 1  # joint position, rad
    VELOCITY = 2  # joint velocity, rad/s
    COMMANDED_VELOCITY = 3  # what the data plane last commanded, rad/s
    PLANNED_POSITION = 4  # from the loaded trajectory, rad


def item_id(robot: int, quantity: int, joint: int) -> int:
    return (robot << 16) | (quantity << 8) | joint


def split_item_id(item: int) -> tuple[int, int, int]:
    """(robot, quantity, joint)."""
    return item >> 16, (item >> 8) & 0xFF, item & 0xFF


# --- packets -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Header:
    destination: int = 0  # logical address, u8
    pid: int = Pid.MRT
    return_address: bytes = b""  # Nrab bytes
    source_process: int = 0  # u32
    destination_process: int = 0  # u32

    def reversed(self) -> Header:
        """The header of the answer: back to where this came from."""
        return Header(
            self.destination, self.pid, self.return_address, self.destination_process, self.source_process
        )


@dataclass(frozen=True)
class Item:
    id: int  # u32, see item_id()
    value: float  # f32
    timestamp: int  # u64 ns, cell clock


@dataclass(frozen=True)
class Wanted:
    id: int
    timestamp: int  # when the value is wanted, ns


@dataclass(frozen=True)
class Query:
    query_id: int
    deadline: int  # ns, cell clock: reply before this or be denied
    inputs: tuple[Item, ...] = ()
    outputs: tuple[Wanted, ...] = ()


@dataclass(frozen=True)
class Reply:
    query_id: int
    items: tuple[Item, ...] = ()


@dataclass(frozen=True)
class Denied:
    query_id: int
    explanation: int


@dataclass(frozen=True)
class Cancel:
    query_id: int


@dataclass(frozen=True)
class TimeRequest:
    t1: int  # the asker's clock when sent, ns


@dataclass(frozen=True)
class TimeResponse:
    t1: int  # echoed
    t2: int  # the master's clock when the request arrived
    t3: int  # the master's clock when the response left


@dataclass(frozen=True)
class PidQuery:
    pid: int = 0  # PID_SUPPORTED_QUERY: the one asked about (PID_LIST_QUERY: unused)


@dataclass(frozen=True)
class PidReply:
    pids: tuple[int, ...] = ()  # supported: the one asked about if supported, else (); list: all


@dataclass(frozen=True)
class ErrorReply:
    """UNKNOWN_PID_REPLY, UNKNOWN_PACKET_TYPE_REPLY or INVALID_DATA_CRC_REPLY: the offending value."""

    value: int  # the unknown pid or packet type; for a bad data CRC, the CRC received


Body = Query | Reply | Denied | Cancel | TimeRequest | TimeResponse | PidQuery | PidReply | ErrorReply


@dataclass(frozen=True)
class Packet:
    header: Header
    type: int
    body: Body
    raw_cargo: bytes = field(default=b"", compare=False)


class PacketError(Exception):
    """A datagram that is not a valid packet; `reply` is the packet to answer with (None: drop)."""

    def __init__(self, why: str, reply: Packet | None = None, counter: str = "malformed") -> None:
        super().__init__(why)
        self.why, self.reply, self.counter = why, reply, counter


# --- cargo codecs ----------------------------------------------------------------------------------

_ITEM = struct.Struct("!IfQ")
_WANTED = struct.Struct("!IQ")
_U32 = struct.Struct("!I")
_QHEAD = struct.Struct("!IQ")


def _items(items: tuple[Item, ...]) -> bytes:
    return _U32.pack(len(items)) + b"".join(_ITEM.pack(i.id, i.value, i.timestamp) for i in items)


def encode_body(body: Body) -> tuple[int, bytes]:
    """(packet type, cargo)."""
    match body:
        case Query():
            wanted = b"".join(_WANTED.pack(w.id, w.timestamp) for w in body.outputs)
            outs = _U32.pack(len(body.outputs)) + wanted
            cargo = _QHEAD.pack(body.query_id, body.deadline) + _items(body.inputs) + outs
            return PacketType.TIME_BOUNDED_QUERY, cargo
        case Reply():
            return PacketType.TIME_BOUNDED_QUERY_REPLY, _U32.pack(body.query_id) + _items(body.items)
        case Denied():
            return PacketType.TIME_BOUNDED_QUERY_DENIAL, struct.pack("!IH", body.query_id, body.explanation)
        case Cancel():
            return PacketType.TIME_BOUNDED_QUERY_CANCELLATION, _U32.pack(body.query_id)
        case TimeRequest():
            return PacketType.TIME_REQUEST, struct.pack("!Q", body.t1)
        case TimeResponse():
            return PacketType.TIME_RESPONSE, struct.pack("!QQQ", body.t1, body.t2, body.t3)
        case PidQuery():
            kind = PacketType.PID_SUPPORTED_QUERY if body.pid else PacketType.PID_LIST_QUERY
            return kind, (struct.pack("!B", body.pid) if body.pid else b"")
        case PidReply():
            return PacketType.PID_LIST_REPLY, struct.pack("!B", len(body.pids)) + bytes(body.pids)
        case ErrorReply():
            raise ValueError("error replies need their type: use encode(..., type=)")
    raise TypeError(f"not a packet body: {body!r}")


def encode(header: Header, body: Body, type: int | None = None) -> bytes:
    """The datagram for a packet; type is needed for ErrorReply and to answer PID_SUPPORTED_QUERY."""
    if isinstance(body, ErrorReply):
        if type is None:
            raise ValueError("an ErrorReply needs its packet type")
        width = "!H" if type == PacketType.UNKNOWN_PACKET_TYPE_REPLY else "!B"  # a packet type, or a u8
        kind, cargo = type, struct.pack(width, body.value)
    else:
        kind, cargo = encode_body(body)
        if type is not None:
            kind = type
    rab = bytes(header.return_address)
    if len(rab) > 255:
        raise ValueError("at most 255 return address bytes")
    head = struct.pack("!BBB", header.destination, header.pid, len(rab)) + rab
    head += struct.pack("!II", header.source_process, header.destination_process)
    data = struct.pack("!BH", 0, kind) + cargo
    return head + bytes([crc8(head)]) + data + bytes([crc8(data)])


def _take(buf: memoryview, n: int, what: str) -> tuple[memoryview, memoryview]:
    if len(buf) < n:
        raise ValueError(f"{what}: {n} bytes needed, {len(buf)} left")
    return buf[:n], buf[n:]


def decode(datagram: bytes | bytearray | memoryview, known_pids: frozenset[int] | None = None) -> Packet:
    """A datagram -> Packet; PacketError (with the reply to send, if any) otherwise."""
    buf = memoryview(bytes(datagram))
    # --- header: a bad header CRC means the return path cannot be trusted: drop -----------------
    if len(buf) < 3:
        raise PacketError("shorter than a header", counter="bad_header")
    nrab = buf[2]
    head_len = 3 + nrab + 8
    if len(buf) < head_len + 1:
        raise PacketError("header cut short", counter="bad_header")
    head = buf[:head_len]
    if crc8(head) != buf[head_len]:
        raise PacketError("header CRC mismatch", counter="bad_header_crc")
    src, dst = struct.unpack_from("!II", head, 3 + nrab)
    header = Header(buf[0], buf[1], bytes(buf[3 : 3 + nrab]), src, dst)
    answer = header.reversed()
    pids = known_pids if known_pids is not None else frozenset(int(p) for p in Pid)
    if header.pid not in pids:
        raise PacketError(
            f"unknown protocol id 0x{header.pid:02X}",
            Packet(answer, PacketType.UNKNOWN_PID_REPLY, ErrorReply(header.pid)),
            "unknown_pid",
        )
    data = buf[head_len + 1 :]
    if len(data) < 4:
        raise PacketError("no data part", counter="malformed")
    if crc8(data[:-1]) != data[-1]:
        raise PacketError(
            "data CRC mismatch",
            Packet(answer, PacketType.INVALID_DATA_CRC_REPLY, ErrorReply(data[-1])),
            "bad_data_crc",
        )
    kind = struct.unpack_from("!H", data, 1)[0]
    cargo = data[3:-1]
    try:
        body = _decode_cargo(kind, cargo)
    except KeyError:
        raise PacketError(
            f"unknown packet type 0x{kind:04X}",
            Packet(answer, PacketType.UNKNOWN_PACKET_TYPE_REPLY, ErrorReply(kind)),
            "unknown_type",
        ) from None
    except (ValueError, struct.error) as exc:
        raise PacketError(f"packet type 0x{kind:04X}: {exc}", counter="malformed") from None
    return Packet(header, kind, body, bytes(cargo))


def _decode_items(buf: memoryview, what: str) -> tuple[tuple[Item, ...], memoryview]:
    n_raw, buf = _take(buf, 4, what)
    n = _U32.unpack(n_raw)[0]
    raw, buf = _take(buf, n * _ITEM.size, f"{n} {what}")
    return tuple(Item(*t) for t in _ITEM.iter_unpack(raw)), buf


def _done(rest: memoryview, kind: str) -> None:
    if len(rest):
        raise ValueError(f"{len(rest)} bytes after the {kind} cargo")


def _decode_cargo(kind: int, cargo: memoryview) -> Body:
    if kind == PacketType.TIME_BOUNDED_QUERY:
        qh, rest = _take(cargo, _QHEAD.size, "query head")
        qid, deadline = _QHEAD.unpack(qh)
        inputs, rest = _decode_items(rest, "input items")
        n_raw, rest = _take(rest, 4, "output count")
        n = _U32.unpack(n_raw)[0]
        raw, rest = _take(rest, n * _WANTED.size, f"{n} output items")
        _done(rest, "query")
        return Query(qid, deadline, inputs, tuple(Wanted(*t) for t in _WANTED.iter_unpack(raw)))
    if kind == PacketType.TIME_BOUNDED_QUERY_REPLY:
        qid_raw, rest = _take(cargo, 4, "query id")
        items, rest = _decode_items(rest, "items")
        _done(rest, "reply")
        return Reply(_U32.unpack(qid_raw)[0], items)
    if kind == PacketType.TIME_BOUNDED_QUERY_DENIAL:
        raw, rest = _take(cargo, 6, "denial")
        _done(rest, "denial")
        qid, why = struct.unpack("!IH", raw)
        return Denied(qid, why)
    if kind == PacketType.TIME_BOUNDED_QUERY_CANCELLATION:
        raw, rest = _take(cargo, 4, "cancellation")
        _done(rest, "cancellation")
        return Cancel(_U32.unpack(raw)[0])
    if kind == PacketType.TIME_REQUEST:
        raw, rest = _take(cargo, 8, "time request")
        _done(rest, "time request")
        return TimeRequest(struct.unpack("!Q", raw)[0])
    if kind == PacketType.TIME_RESPONSE:
        raw, rest = _take(cargo, 24, "time response")
        _done(rest, "time response")
        return TimeResponse(*struct.unpack("!QQQ", raw))
    if kind == PacketType.PID_SUPPORTED_QUERY:
        raw, rest = _take(cargo, 1, "pid")
        _done(rest, "pid query")
        return PidQuery(raw[0])
    if kind == PacketType.PID_LIST_QUERY:
        _done(cargo, "pid list query")
        return PidQuery(0)
    if kind in (PacketType.PID_SUPPORTED_REPLY, PacketType.PID_LIST_REPLY):
        raw, rest = _take(cargo, 1, "pid count")
        pids, rest = _take(rest, raw[0], "pids")
        _done(rest, "pid reply")
        return PidReply(tuple(pids))
    if kind in (PacketType.UNKNOWN_PID_REPLY, PacketType.INVALID_DATA_CRC_REPLY):
        raw, rest = _take(cargo, 1, "value")
        _done(rest, "error reply")
        return ErrorReply(raw[0])
    if kind == PacketType.UNKNOWN_PACKET_TYPE_REPLY:
        raw, rest = _take(cargo, 2, "value")
        _done(rest, "error reply")
        return ErrorReply(struct.unpack("!H", raw)[0])
    raise KeyError(kind)
