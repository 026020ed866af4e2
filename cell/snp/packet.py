"""SnP packets (SpW-SnP-MR), sans IO: bytes <-> packet objects, CRCs checked and made.

One packet per UDP datagram (the SpaceWire end of packet is the datagram's
end); layout and field meanings in docs/protocols/snp-mrt.md.  Multi-byte
fields are big-endian.  decode() never raises anything but PacketError, whose
`reply` says what the handler should answer (or None: drop), so that no
packet can stop a service.

One module, over 600 lines, on purpose: it is the one wire format, every packet type's layout, codec
and CRC beside the others', as docs/protocols/snp-mrt.md lists them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from typing import NamedTuple

import anycrc

# --- the RMAP CRC-8 (ECSS-E-ST-50-52C): x^8 + x^2 + x + 1, init 0, bytes LSB first, no final XOR --------

_RMAP_CRC = anycrc.CRC(width=8, poly=0x07, init=0, refin=True, refout=True, xorout=0)


def crc8(data: bytes | bytearray | memoryview) -> int:
    """The RMAP CRC of data (anycrc, in C: 0.4 us for 80 bytes against 6 us table by table)."""
    return _RMAP_CRC.calc(data)


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
    # SnP-MrT initialisation: topology exploration and automatic configuration
    NODE_INFO_QUERY = 0x0030
    NODE_INFO_REPLY = 0x0031
    CONFIGURE = 0x0032
    CONFIGURE_REPLY = 0x0033
    # SnP-TSP (protocol 0xF1): a two-way time exchange
    TIME_REQUEST = 0x0010
    TIME_RESPONSE = 0x0011
    TIME_SUBSCRIBE = 0x0012  # "beacons every P ns, to a precision of E ns"
    TIME_SUBSCRIBE_REPLY = 0x0013
    TIME_BEACON = 0x0014
    TIME_FOLLOW_UP = 0x0015  # two-step stamping: when a beacon or response really left
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


class Level(IntEnum):
    """How much of a protocol a node implements (PID management: "to what level?")."""

    PARTIAL = 1
    FULL = 2


class ModuleKind(IntEnum):
    MASTER = 1
    JOINT = 2


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


# The packets of the 1 kHz cycle (headers, items, queries, replies) are named tuples: immutable
# values like the dataclasses below, made four times as fast (a decoded query is five of them).


DEFAULT_LA = 0xFE  # SpaceWire's default logical address (a node addressed by path)


class Header(NamedTuple):
    destination: int = 0  # logical address, u8
    pid: int = Pid.MRT
    return_address: bytes = b""  # Nrab bytes
    source_process: int = 0  # u32
    destination_process: int = 0  # u32

    def reversed(self) -> Header:
        """The header of the answer: the processes swapped, routed back by this packet's return
        address (spacewire.routed_reply puts it in front as path addresses), so it carries none
        itself, and addressed to the default logical address (an SnP-MrT header does not carry the
        asker's)."""
        return Header(DEFAULT_LA, self.pid, b"", self.destination_process, self.source_process)


class Item(NamedTuple):
    id: int  # u32, see item_id()
    value: float  # f32
    timestamp: int  # u64 ns, cell clock


class Wanted(NamedTuple):
    id: int
    timestamp: int  # when the value is wanted, ns


class Query(NamedTuple):
    query_id: int
    deadline: int  # ns, cell clock: reply before this or be denied
    inputs: tuple[Item, ...] = ()
    outputs: tuple[Wanted, ...] = ()


class Reply(NamedTuple):
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
    levels: tuple[int, ...] | None = None  # per pid (Level); None: all FULL

    def __post_init__(self) -> None:
        if self.levels is None:
            object.__setattr__(self, "levels", (Level.FULL,) * len(self.pids))
        elif len(self.levels) != len(self.pids):
            raise ValueError("one level per pid")


@dataclass(frozen=True)
class NodeInfoQuery:
    """Topology exploration: "who are you, what are you plugged to, what do you offer?"."""


@dataclass(frozen=True)
class NodeInfo:
    module_id: int  # u32: the module's own serial number
    kind: int  # u8: ModuleKind
    plugged_to: int  # u32: the module id of the module this one is plugged to (0: the base plate)
    port: int  # u8: which port of it
    items: tuple[int, ...] = ()  # item ids it offers as inputs (u16 count, u32 each)
    joint: int = 0xFF  # u8: the joint index it is configured as (0xFF: not configured)


@dataclass(frozen=True)
class Configure:
    """Automatic configuration: the module's place in the cycle and its control parameters."""

    joint: int  # u8: its joint index (its depth in the chain from the base plate)
    period_ns: int  # u32: the cycle period
    phase_ns: int  # u32: where in the period its cycle starts
    budget_ns: int  # u32: each query's deadline after the cycle start
    params: tuple[float, ...] = ()  # f32 each (u8 count): control parameters


@dataclass(frozen=True)
class Configured:
    joint: int  # u8
    status: int = 0  # u8: 0 configured, else why not


@dataclass(frozen=True)
class TimeSubscribe:
    """SnP-TSP: time beacons every period_ns, the asker wanting its clock within precision_ns."""

    period_ns: int  # u32
    precision_ns: int  # u32


@dataclass(frozen=True)
class TimeSubscribed:
    period_ns: int  # u32: the period granted (0: refused)
    precision_ns: int  # u32: the precision the master can offer (its beacons' jitter), ns


@dataclass(frozen=True)
class TimeBeacon:
    seq: int  # u32
    t_master: int  # u64: the master's clock as the beacon left, ns


@dataclass(frozen=True)
class TimeFollowUp:
    """Two-step time stamping (PTP's Follow_Up): when a TIME_BEACON or TIME_RESPONSE the receiver
    just had left its sender, by the sender's kernel; the time in that packet is the sender's
    earlier one-step estimate."""

    of: int  # u16: the packet type it follows up (TIME_BEACON or TIME_RESPONSE)
    ref: int  # u64: which one: the beacon's seq, or the response's t1
    t: int  # u64: its departure, the sender's clock, ns


@dataclass(frozen=True)
class ErrorReply:
    """UNKNOWN_PID_REPLY, UNKNOWN_PACKET_TYPE_REPLY or INVALID_DATA_CRC_REPLY: the offending value."""

    value: int  # the unknown pid or packet type; for a bad data CRC, the CRC received


Body = (
    Query
    | Reply
    | Denied
    | Cancel
    | TimeRequest
    | TimeResponse
    | PidQuery
    | PidReply
    | ErrorReply
    | NodeInfoQuery
    | NodeInfo
    | Configure
    | Configured
    | TimeSubscribe
    | TimeSubscribed
    | TimeBeacon
    | TimeFollowUp
)


@dataclass(frozen=True)
class Packet:
    header: Header
    type: int
    body: Body
    raw_cargo: bytes = field(default=b"", compare=False)


class Refusal(StrEnum):
    """Why a datagram was not a packet: the name it is counted under (see handler.HandlerCounters)."""

    BAD_HEADER = "bad_header"
    BAD_HEADER_CRC = "bad_header_crc"
    UNKNOWN_PID = "unknown_pid"
    MALFORMED = "malformed"
    BAD_DATA_CRC = "bad_data_crc"
    UNKNOWN_TYPE = "unknown_type"


class PacketError(Exception):
    """A datagram that is not a valid packet; `reply` is the packet to answer with (None: drop)."""

    def __init__(self, why: str, reply: Packet | None = None, counter: Refusal = Refusal.MALFORMED) -> None:
        super().__init__(why)
        self.why, self.reply, self.counter = why, reply, counter


# --- cargo codecs ----------------------------------------------------------------------------------

_ITEM = struct.Struct("!IfQ")
_WANTED = struct.Struct("!IQ")
_U32 = struct.Struct("!I")
_QHEAD = struct.Struct("!IQ")
_NODE = struct.Struct("!IBIBB")  # module id, kind, plugged to, port, joint
_CONF = struct.Struct("!BIII")  # joint, period, phase, budget
_BEACON = struct.Struct("!IQ")
_FOLLOW_UP = struct.Struct("!HQQ")


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
            pairs = bytes(b for pl in zip(body.pids, body.levels or (), strict=True) for b in pl)
            return PacketType.PID_LIST_REPLY, struct.pack("!B", len(body.pids)) + pairs
        case NodeInfoQuery():
            return PacketType.NODE_INFO_QUERY, b""
        case NodeInfo():
            head = _NODE.pack(body.module_id, body.kind, body.plugged_to, body.port, body.joint)
            items = struct.pack(f"!H{len(body.items)}I", len(body.items), *body.items)
            return PacketType.NODE_INFO_REPLY, head + items
        case Configure():
            head = _CONF.pack(body.joint, body.period_ns, body.phase_ns, body.budget_ns)
            params = struct.pack(f"!B{len(body.params)}f", len(body.params), *body.params)
            return PacketType.CONFIGURE, head + params
        case Configured():
            return PacketType.CONFIGURE_REPLY, struct.pack("!BB", body.joint, body.status)
        case TimeSubscribe():
            return PacketType.TIME_SUBSCRIBE, struct.pack("!II", body.period_ns, body.precision_ns)
        case TimeSubscribed():
            return PacketType.TIME_SUBSCRIBE_REPLY, struct.pack("!II", body.period_ns, body.precision_ns)
        case TimeBeacon():
            return PacketType.TIME_BEACON, _BEACON.pack(body.seq, body.t_master)
        case TimeFollowUp():
            return PacketType.TIME_FOLLOW_UP, _FOLLOW_UP.pack(body.of, body.ref, body.t)
        case ErrorReply():
            raise ValueError("error replies need their type: use encode(..., type=)")
    raise TypeError(f"not a packet body: {body!r}")


def encode(header: Header, body: Body, type: int | None = None) -> bytes:
    """The datagram for a packet; type is needed for ErrorReply and to answer PID_SUPPORTED_QUERY."""
    if type is None and not header.return_address:
        if body.__class__ is Query:  # the cycle's packets: one pack each (3 us against 9)
            return _encode_query(header, body)
        if body.__class__ is Reply:
            return _encode_reply(header, body)
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


# where each SnP-TSP packet's departure time (t1, t3, t_master) sits in its data field
_DEPARTURE: dict[int, int] = {
    PacketType.TIME_REQUEST: 3,
    PacketType.TIME_RESPONSE: 19,
    PacketType.TIME_BEACON: 7,
}
_U64 = struct.Struct("!Q")


def stamp_departure(datagram: bytes, t: int) -> bytes:
    """One-step time stamping: a TIME_REQUEST, TIME_RESPONSE or TIME_BEACON with its departure time
    (t1, t3, t_master) set to t and its data CRC made anew; any other datagram as it is.

    The link calls it as it sends, as a one-step PTP port writes the time into a Sync as it leaves.
    Dated when made instead, a packet carries its encoding and whatever the sender did before
    sending it (7-15 us in Python here, and not the same on every path): the servo takes half the
    shortest round trip for a beacon's path delay, so any difference between the paths' stamp-to-
    wire times is a steady clock error."""
    got = time_packet(datagram)
    if got is None:
        return datagram
    kind, data = got
    buf = bytearray(datagram)
    _U64.pack_into(buf, data + _DEPARTURE[kind], t)
    buf[-1] = crc8(memoryview(buf)[data:-1])
    return bytes(buf)


def time_packet(datagram: bytes) -> tuple[int, int] | None:
    """(packet type, data offset) of an SnP-TSP TIME_REQUEST, TIME_RESPONSE or TIME_BEACON (the
    packets that carry their own departure); None for any other datagram."""
    if len(datagram) < 15 or datagram[1] != Pid.TSP:
        return None
    data = 12 + datagram[2]
    kind = int.from_bytes(datagram[data + 1 : data + 3], "big")
    at = _DEPARTURE.get(kind)
    return None if at is None or len(datagram) < data + at + 9 else (kind, data)


def follow_up(datagram: bytes, t: int) -> bytes | None:
    """Two-step time stamping: the TIME_FOLLOW_UP saying that this TIME_BEACON or TIME_RESPONSE
    (as sent, one-step stamped or not) left at t, for the same receiver; None for any other
    datagram.  A one-step stamp is read in the sender's code before its send call, which then
    takes 7-20 us here to reach the wire; the kernel's stamp (SO_TIMESTAMPING) is read after it
    and is within a microsecond of the receiver's."""
    got = time_packet(datagram)
    if got is None or got[0] == PacketType.TIME_REQUEST:  # (a request's departure is the asker's own)
        return None
    kind, data = got
    if kind == PacketType.TIME_BEACON:
        ref = _U32.unpack_from(datagram, data + 3)[0]  # its seq
    else:
        ref = _U64.unpack_from(datagram, data + 3)[0]  # the response's t1
    src, dst = struct.unpack_from("!II", datagram, 3 + datagram[2])
    back = Header(datagram[0], Pid.TSP, bytes(datagram[3 : 3 + datagram[2]]), src, dst)
    return encode(back, TimeFollowUp(kind, ref, t))


# --- the fast path: the cycle's queries and replies, each shape one struct ---------------------------
#
# A query or reply with no return address and a given number of items has a fixed layout, so
# that the whole datagram (header, its CRC, data, its CRC) is one precompiled struct, as a P4
# parser's fixed header stack.  The modular robot's 1 kHz cycle packs and parses its packets with
# these directly (flat tuples, no objects); encode() and decode() take the same path for every
# query and reply that fits one.

_FAST_MAX = 8  # item counts up to this get a shape of their own


class QueryShape:
    """A TIME_BOUNDED_QUERY with n_in inputs, n_out outputs and no return address.

    parse() returns the struct's fields: destination, pid, 0, source process, destination
    process, header CRC, 0, type, query id, deadline, n_in, (id, value, timestamp) per input,
    n_out, (id, timestamp) per output, data CRC; or None if the datagram is not this shape with
    both CRCs right."""

    TYPE = 0x0001

    def __init__(self, n_in: int, n_out: int) -> None:
        self.n_in, self.n_out = n_in, n_out
        self.struct = struct.Struct(f"!BBBIIBBHIQI{'IfQ' * n_in}I{'IQ' * n_out}B")
        self.size = self.struct.size
        self._i_out = 11 + 3 * n_in  # the output count's field

    def pack(self, destination: int, pid: int, source: int, dest_process: int, query_id: int,
             deadline: int, inputs: tuple, outputs: tuple) -> bytes:  # fmt: skip
        """inputs: id, value, timestamp for each, flat; outputs: id, timestamp for each."""
        buf = bytearray(self.size)
        self.struct.pack_into(
            buf, 0, destination, pid, 0, source, dest_process, 0, 0, self.TYPE, query_id, deadline,
            self.n_in, *inputs, self.n_out, *outputs, 0,
        )  # fmt: skip
        return _sealed(buf)

    def parse(self, data: bytes) -> tuple | None:
        if not _fits(data, self.size, self.TYPE):
            return None
        f = self.struct.unpack(data)
        return f if f[10] == self.n_in and f[self._i_out] == self.n_out else None


class ReplyShape:
    """A TIME_BOUNDED_QUERY_REPLY with n items and no return address; parse() returns destination,
    pid, 0, source process, destination process, header CRC, 0, type, query id, n, (id, value,
    timestamp) per item, data CRC."""

    TYPE = 0x0002

    def __init__(self, n: int) -> None:
        self.n = n
        self.struct = struct.Struct(f"!BBBIIBBHII{'IfQ' * n}B")
        self.size = self.struct.size

    def pack(self, destination: int, pid: int, source: int, dest_process: int, query_id: int,
             items: tuple) -> bytes:  # fmt: skip
        buf = bytearray(self.size)
        self.struct.pack_into(
            buf, 0, destination, pid, 0, source, dest_process, 0, 0, self.TYPE, query_id, self.n, *items, 0
        )
        return _sealed(buf)

    def parse(self, data: bytes) -> tuple | None:
        if not _fits(data, self.size, self.TYPE):
            return None
        f = self.struct.unpack(data)
        return f if f[9] == self.n else None


def _fits(data: bytes, size: int, kind: int) -> bool:
    """A datagram of a shape's size and packet type, no return address, both CRCs right."""
    if len(data) != size or data[2] or data[14] != kind or data[13]:
        return False
    mv = memoryview(data)
    return crc8(mv[:11]) == data[11] and crc8(mv[12:-1]) == data[-1]


def _sealed(buf: bytearray) -> bytes:
    """Fill in the two CRCs of a datagram packed with no return address."""
    mv = memoryview(buf)
    buf[11] = crc8(mv[:11])
    buf[-1] = crc8(mv[12:-1])
    return bytes(buf)


_query_shapes: dict[tuple[int, int], QueryShape] = {}
_reply_shapes: dict[int, ReplyShape] = {}


def query_shape(n_in: int, n_out: int) -> QueryShape:
    s = _query_shapes.get((n_in, n_out))
    if s is None:
        s = _query_shapes[n_in, n_out] = QueryShape(n_in, n_out)
    return s


def reply_shape(n: int) -> ReplyShape:
    s = _reply_shapes.get(n)
    if s is None:
        s = _reply_shapes[n] = ReplyShape(n)
    return s


def _encode_query(h: Header, q: Query) -> bytes:
    n_in, n_out = len(q.inputs), len(q.outputs)
    if n_in > _FAST_MAX or n_out > _FAST_MAX:
        return encode(h, q, PacketType.TIME_BOUNDED_QUERY)
    ins = tuple(x for i in q.inputs for x in i)
    outs = tuple(x for w in q.outputs for x in w)
    shape = query_shape(n_in, n_out)
    return shape.pack(
        h.destination, h.pid, h.source_process, h.destination_process, q.query_id, q.deadline, ins, outs
    )


def _encode_reply(h: Header, r: Reply) -> bytes:
    if len(r.items) > _FAST_MAX:
        return encode(h, r, PacketType.TIME_BOUNDED_QUERY_REPLY)
    items = tuple(x for i in r.items for x in i)
    return reply_shape(len(r.items)).pack(
        h.destination, h.pid, h.source_process, h.destination_process, r.query_id, items
    )


def _decode_fast(buf: bytes, pids: frozenset[int]) -> Packet | None:
    """A query or reply that fits a shape, with a known pid; else None (the full decoder then
    says what is wrong with it, if anything)."""
    if len(buf) < 24 or buf[2] or buf[13] or buf[1] not in pids:
        return None
    kind = buf[14]
    if kind == QueryShape.TYPE:
        n_in = int.from_bytes(buf[27:31], "big")
        if n_in > _FAST_MAX or len(buf) < 36 + 16 * n_in:
            return None
        n_out = (len(buf) - 36 - 16 * n_in) // 12
        if n_out > _FAST_MAX or (f := query_shape(n_in, n_out).parse(buf)) is None:
            return None
        o = 12 + 3 * n_in
        inputs = tuple(Item(f[k], f[k + 1], f[k + 2]) for k in range(11, o - 1, 3))
        body: Body = Query(
            f[8], f[9], inputs, tuple(Wanted(f[k], f[k + 1]) for k in range(o, o + 2 * n_out, 2))
        )
    elif kind == ReplyShape.TYPE:
        n = (len(buf) - 24) // 16
        if n > _FAST_MAX or (f := reply_shape(n).parse(buf)) is None:
            return None
        body = Reply(f[8], tuple(Item(f[k], f[k + 1], f[k + 2]) for k in range(10, 10 + 3 * n, 3)))
    else:
        return None
    return Packet(Header(f[0], f[1], b"", f[3], f[4]), kind, body, buf[15:-1])


def _take(buf: memoryview, n: int, what: str) -> tuple[memoryview, memoryview]:
    if len(buf) < n:
        raise ValueError(f"{what}: {n} bytes needed, {len(buf)} left")
    return buf[:n], buf[n:]


_ALL_PIDS = frozenset(int(p) for p in Pid)


def decode(datagram: bytes | bytearray | memoryview, known_pids: frozenset[int] | None = None) -> Packet:
    """A datagram -> Packet; PacketError (with the reply to send, if any) otherwise."""
    raw = bytes(datagram)
    pids = known_pids if known_pids is not None else _ALL_PIDS
    fast = _decode_fast(raw, pids)
    if fast is not None:
        return fast
    buf = memoryview(raw)
    # --- header: a bad header CRC means the return path cannot be trusted: drop -----------------
    if len(buf) < 3:
        raise PacketError("shorter than a header", counter=Refusal.BAD_HEADER)
    nrab = buf[2]
    head_len = 3 + nrab + 8
    if len(buf) < head_len + 1:
        raise PacketError("header cut short", counter=Refusal.BAD_HEADER)
    head = buf[:head_len]
    if crc8(head) != buf[head_len]:
        raise PacketError("header CRC mismatch", counter=Refusal.BAD_HEADER_CRC)
    src, dst = struct.unpack_from("!II", head, 3 + nrab)
    header = Header(buf[0], buf[1], bytes(buf[3 : 3 + nrab]), src, dst)
    answer = header.reversed()
    if header.pid not in pids:
        raise PacketError(
            f"unknown protocol id 0x{header.pid:02X}",
            Packet(answer, PacketType.UNKNOWN_PID_REPLY, ErrorReply(header.pid)),
            Refusal.UNKNOWN_PID,
        )
    data = buf[head_len + 1 :]
    if len(data) < 4:
        raise PacketError("no data part", counter=Refusal.MALFORMED)
    if crc8(data[:-1]) != data[-1]:
        raise PacketError(
            "data CRC mismatch",
            Packet(answer, PacketType.INVALID_DATA_CRC_REPLY, ErrorReply(data[-1])),
            Refusal.BAD_DATA_CRC,
        )
    kind = struct.unpack_from("!H", data, 1)[0]
    cargo = data[3:-1]
    try:
        body = _decode_cargo(kind, cargo)
    except KeyError:
        raise PacketError(
            f"unknown packet type 0x{kind:04X}",
            Packet(answer, PacketType.UNKNOWN_PACKET_TYPE_REPLY, ErrorReply(kind)),
            Refusal.UNKNOWN_TYPE,
        ) from None
    except (ValueError, struct.error) as exc:
        raise PacketError(f"packet type 0x{kind:04X}: {exc}", counter=Refusal.MALFORMED) from None
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
        pairs, rest = _take(rest, 2 * raw[0], "pids and levels")
        _done(rest, "pid reply")
        return PidReply(tuple(pairs[0::2]), tuple(pairs[1::2]))
    if kind == PacketType.NODE_INFO_QUERY:
        _done(cargo, "node info query")
        return NodeInfoQuery()
    if kind == PacketType.NODE_INFO_REPLY:
        head, rest = _take(cargo, _NODE.size, "node info")
        module_id, mkind, plugged_to, port, joint = _NODE.unpack(head)
        n_raw, rest = _take(rest, 2, "item count")
        n = struct.unpack("!H", n_raw)[0]
        raw, rest = _take(rest, 4 * n, f"{n} items")
        _done(rest, "node info")
        return NodeInfo(module_id, mkind, plugged_to, port, struct.unpack(f"!{n}I", raw), joint)
    if kind == PacketType.CONFIGURE:
        head, rest = _take(cargo, _CONF.size, "configuration")
        n_raw, rest = _take(rest, 1, "parameter count")
        raw, rest = _take(rest, 4 * n_raw[0], f"{n_raw[0]} parameters")
        _done(rest, "configuration")
        joint, period_ns, phase_ns, budget_ns = _CONF.unpack(head)
        return Configure(joint, period_ns, phase_ns, budget_ns, struct.unpack(f"!{n_raw[0]}f", raw))
    if kind == PacketType.CONFIGURE_REPLY:
        raw, rest = _take(cargo, 2, "configured")
        _done(rest, "configured")
        return Configured(raw[0], raw[1])
    if kind in (PacketType.TIME_SUBSCRIBE, PacketType.TIME_SUBSCRIBE_REPLY):
        raw, rest = _take(cargo, 8, "subscription")
        _done(rest, "subscription")
        cls = TimeSubscribe if kind == PacketType.TIME_SUBSCRIBE else TimeSubscribed
        return cls(*struct.unpack("!II", raw))
    if kind == PacketType.TIME_BEACON:
        raw, rest = _take(cargo, _BEACON.size, "beacon")
        _done(rest, "beacon")
        return TimeBeacon(*_BEACON.unpack(raw))
    if kind == PacketType.TIME_FOLLOW_UP:
        raw, rest = _take(cargo, _FOLLOW_UP.size, "follow-up")
        _done(rest, "follow-up")
        return TimeFollowUp(*_FOLLOW_UP.unpack(raw))
    if kind in (PacketType.UNKNOWN_PID_REPLY, PacketType.INVALID_DATA_CRC_REPLY):
        raw, rest = _take(cargo, 1, "value")
        _done(rest, "error reply")
        return ErrorReply(raw[0])
    if kind == PacketType.UNKNOWN_PACKET_TYPE_REPLY:
        raw, rest = _take(cargo, 2, "value")
        _done(rest, "error reply")
        return ErrorReply(struct.unpack("!H", raw)[0])
    raise KeyError(kind)
