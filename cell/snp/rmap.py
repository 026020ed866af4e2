"""RMAP (ECSS-E-ST-50-52C), sans IO: acknowledged writes, the slides' baseline, and reads, as the
master reads a router's configuration port to find the network (cell.snp.spacewire.Explorer).

The SpW-SnP-MR slides weigh their time-bounded queries against carrying the modular robot's
A, B, C and D messages as acknowledged RMAP writes with a fixed timeout and a retry: two
packets per message (8 T_M a cycle against the queries' 4 T_M), 16 T_M with one retry.
This is that baseline, on the same UDP transport: the write command and its reply, a target
(memory written at addresses, a reply per write) and an initiator (its writes in flight,
resent after a fixed timeout, given up after the last retry).

Layouts (one packet per datagram, no SpaceWire path address):
- write command: target logical address, protocol id 0x01, instruction, key, reply address
  (0/4/8/12 bytes), initiator logical address, transaction id u16, extended address u8,
  address u32, data length u24, header CRC, data, data CRC;
- write reply: initiator logical address, protocol id, instruction, status, target logical
  address, transaction id u16, header CRC;
- read command: a write command's header (its write bit clear), no data;
- read reply: a write reply's fields, a reserved byte, data length u24, header CRC, data, data CRC.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

from cell.counters import Counters
from cell.snp.packet import crc8

PROTOCOL_ID = 0x01
# instruction bits: [7:6] packet type (01 command, 00 reply), 5 write, 4 verify, 3 reply, 2 increment
_COMMAND, _WRITE, _VERIFY, _REPLY, _INCREMENT = 0x40, 0x20, 0x10, 0x08, 0x04
_CMD_TAIL = struct.Struct("!BHBI")  # initiator, transaction id, extended address, address
_REPLY_BODY = struct.Struct("!BBBBBH")  # initiator, pid, instruction, status, target, transaction id


class Status(IntEnum):
    SUCCESS = 0
    GENERAL_ERROR = 1
    UNUSED_TYPE = 2
    INVALID_KEY = 3
    INVALID_DATA_CRC = 4
    EARLY_EOP = 5
    TOO_MUCH_DATA = 6
    NOT_AUTHORISED = 10
    INVALID_TARGET = 12


class RmapError(Exception):
    """Not an RMAP packet this end can take (dropped and counted: an RMAP target with a bad
    header CRC cannot trust the reply address); `status` is what a reply would say, if any."""

    def __init__(self, why: str, status: Status | None = None) -> None:
        super().__init__(why)
        self.status = status


@dataclass(frozen=True)
class Write:
    target: int  # target logical address
    initiator: int  # initiator logical address
    transaction: int  # u16
    address: int  # u32
    data: bytes
    key: int = 0
    extended: int = 0
    verify: bool = True
    acknowledged: bool = True
    reply_address: bytes = b""


@dataclass(frozen=True)
class WriteReply:
    initiator: int
    target: int
    transaction: int
    status: int = Status.SUCCESS
    instruction: int = _WRITE | _VERIFY | _REPLY | _INCREMENT


def encode_write(w: Write) -> bytes:
    instr = _COMMAND | _WRITE | _INCREMENT | (_VERIFY if w.verify else 0) | (_REPLY if w.acknowledged else 0)
    tail = _CMD_TAIL.pack(w.initiator, w.transaction, w.extended, w.address)
    head = _command_head(w.target, instr, w.key, w.reply_address, tail, len(w.data))
    return head + w.data + bytes([crc8(w.data)])


@dataclass(frozen=True)
class Read:
    target: int
    initiator: int
    transaction: int
    address: int
    length: int  # bytes wanted
    key: int = 0
    extended: int = 0
    reply_address: bytes = b""


@dataclass(frozen=True)
class ReadReply:
    initiator: int
    target: int
    transaction: int
    data: bytes
    status: int = Status.SUCCESS


def _command_head(target: int, instr: int, key: int, reply_address: bytes, tail: bytes, length: int) -> bytes:
    if len(reply_address) % 4 or len(reply_address) > 12:
        raise ValueError("the reply address is 0, 4, 8 or 12 bytes")
    head = bytes([target, PROTOCOL_ID, instr | len(reply_address) // 4, key]) + reply_address + tail
    head += length.to_bytes(3, "big")
    return head + bytes([crc8(head)])


def encode_read(r: Read) -> bytes:
    tail = _CMD_TAIL.pack(r.initiator, r.transaction, r.extended, r.address)
    return _command_head(r.target, _COMMAND | _REPLY | _INCREMENT, r.key, r.reply_address, tail, r.length)


def encode_read_reply(r: ReadReply) -> bytes:
    head = _REPLY_BODY.pack(r.initiator, PROTOCOL_ID, _REPLY | _INCREMENT, r.status, r.target, r.transaction)
    head += b"\x00" + len(r.data).to_bytes(3, "big")
    return head + bytes([crc8(head)]) + r.data + bytes([crc8(r.data)])


def encode_reply(r: WriteReply) -> bytes:
    head = _REPLY_BODY.pack(r.initiator, PROTOCOL_ID, r.instruction & 0x3F, r.status, r.target, r.transaction)
    return head + bytes([crc8(head)])


def is_rmap(datagram: bytes) -> bool:
    """An RMAP packet by its protocol id, at least as long as the shortest (a write reply)."""
    return len(datagram) >= _REPLY_BODY.size + 1 and datagram[1] == PROTOCOL_ID


def decode(datagram: bytes) -> Write | WriteReply | Read | ReadReply:
    """A write or read command, or its reply; RmapError for anything else."""
    buf = bytes(datagram)
    if len(buf) < 8 or buf[1] != PROTOCOL_ID:
        raise RmapError("not an RMAP packet")
    instr = buf[2]
    if instr & 0xC0 == 0:
        return _decode_reply(buf)
    if instr & 0xC0 != _COMMAND:
        raise RmapError(f"packet type {instr >> 6} is reserved")
    n_reply = 4 * (instr & 0x03)
    head_len = 4 + n_reply + _CMD_TAIL.size + 3
    if len(buf) < head_len + 1:
        raise RmapError("header cut short")
    if crc8(buf[:head_len]) != buf[head_len]:
        raise RmapError("header CRC mismatch")
    initiator, tid, extended, address = _CMD_TAIL.unpack_from(buf, 4 + n_reply)
    length = int.from_bytes(buf[head_len - 3 : head_len], "big")
    reply_address = buf[4 : 4 + n_reply]
    if not instr & _WRITE:
        if len(buf) != head_len + 1:
            raise RmapError(f"a read command is {head_len + 1} bytes, not {len(buf)}")
        if not instr & _REPLY:
            raise RmapError("a read asks for its reply", Status.UNUSED_TYPE)
        return Read(buf[0], initiator, tid, address, length, buf[3], extended, reply_address)
    data = buf[head_len + 1 : -1]
    if len(data) < length:
        raise RmapError(f"{len(data)} data bytes of {length}", Status.EARLY_EOP)
    if len(data) > length:
        raise RmapError(f"{len(data)} data bytes, {length} announced", Status.TOO_MUCH_DATA)
    w = Write(
        buf[0], initiator, tid, address, data, buf[3], extended,
        bool(instr & _VERIFY), bool(instr & _REPLY), reply_address,
    )  # fmt: skip
    if crc8(data) != buf[-1]:
        raise _DataCrc(w)
    return w


def _decode_reply(buf: bytes) -> WriteReply | ReadReply:
    initiator, _, instruction, status, target, tid = _REPLY_BODY.unpack_from(buf)
    if instruction & _WRITE:
        if len(buf) != _REPLY_BODY.size + 1:
            raise RmapError(f"a write reply is {_REPLY_BODY.size + 1} bytes, not {len(buf)}")
        if crc8(buf[:-1]) != buf[-1]:
            raise RmapError("reply header CRC mismatch")
        return WriteReply(initiator, target, tid, status, instruction)
    head_len = _REPLY_BODY.size + 4
    if len(buf) < head_len + 2 or crc8(buf[:head_len]) != buf[head_len]:
        raise RmapError("read reply header cut short or CRC mismatch")
    data = buf[head_len + 1 : -1]
    if len(data) != int.from_bytes(buf[head_len - 3 : head_len], "big") or crc8(data) != buf[-1]:
        raise RmapError("read reply data cut short or CRC mismatch")
    return ReadReply(initiator, target, tid, data, status)


class _DataCrc(RmapError):
    def __init__(self, w: Write) -> None:
        super().__init__("data CRC mismatch", Status.INVALID_DATA_CRC)
        self.write = w


@dataclass(slots=True)
class TargetCounters(Counters):
    writes: int = 0
    replies: int = 0
    errors: int = 0
    dropped: int = 0  # not RMAP, or a reply sent to a target


@dataclass(slots=True)
class InitiatorCounters(Counters):
    writes: int = 0
    acked: int = 0
    retries: int = 0
    failed: int = 0  # given up after the retries
    errors: int = 0
    stray: int = 0  # a reply to no write in flight (late, or not ours)


class Target:
    """An RMAP target: writes land in `memory` (address -> bytes) and call on_write; each
    acknowledged write gets its reply.  Nothing a peer sends raises out of here."""

    def __init__(self, logical_address: int, on_write: Callable[[int, bytes], None], key: int = 0) -> None:
        self.logical_address, self.on_write, self.key = logical_address, on_write, key
        self.memory: dict[int, bytes] = {}
        self.counters = TargetCounters()

    def receive(self, datagram: bytes) -> bytes | None:
        """The reply to send back, if any."""
        try:
            w = decode(datagram)
        except _DataCrc as exc:  # the header is good: the initiator hears why (verified writes)
            self.counters.errors += 1
            w = exc.write
            return encode_reply(self._reply(w, Status.INVALID_DATA_CRC)) if w.acknowledged else None
        except RmapError:
            self.counters.dropped += 1
            return None
        if not isinstance(w, Write):
            self.counters.dropped += 1  # a reply sent to a target
            return None
        status = Status.SUCCESS
        if w.target != self.logical_address:
            status = Status.INVALID_TARGET
        elif w.key != self.key:
            status = Status.INVALID_KEY
        if status == Status.SUCCESS:
            self.memory[w.address] = w.data
            self.counters.writes += 1
            self.on_write(w.address, w.data)
        else:
            self.counters.errors += 1
        if not w.acknowledged:
            return None
        self.counters.replies += 1
        return encode_reply(self._reply(w, status))

    @staticmethod
    def _reply(w: Write, status: Status) -> WriteReply:
        instr = _WRITE | (_VERIFY if w.verify else 0) | _REPLY | _INCREMENT | (len(w.reply_address) // 4)
        return WriteReply(w.initiator, w.target, w.transaction, status, instr)


@dataclass
class _InFlight:
    write: Write
    datagram: bytes
    sent_at: int
    tries: int


class Initiator:
    """An RMAP initiator: acknowledged writes, each resent after `timeout_ns` up to `retries`
    times, then given up (the slides' fixed timeout: it does not know the deadline)."""

    def __init__(self, logical_address: int, timeout_ns: int, retries: int = 1) -> None:
        self.logical_address, self.timeout_ns, self.retries = logical_address, timeout_ns, retries
        self._tid = 0
        self.in_flight: dict[int, _InFlight] = {}
        self.counters = InitiatorCounters()

    def write(self, target: int, address: int, data: bytes, now: int) -> tuple[int, bytes]:
        """(transaction id, datagram to send)."""
        self._tid = (self._tid + 1) & 0xFFFF
        w = Write(target, self.logical_address, self._tid, address, data)
        raw = encode_write(w)
        self.in_flight[self._tid] = _InFlight(w, raw, now, 1)
        self.counters.writes += 1
        return self._tid, raw

    def receive(self, datagram: bytes) -> tuple[int, int] | None:
        """A reply: (transaction id, status) if it closes a write in flight, else None."""
        try:
            r = decode(datagram)
        except RmapError:
            self.counters.errors += 1
            return None
        if not isinstance(r, WriteReply) or r.transaction not in self.in_flight:
            self.counters.stray += 1  # late (already retried and acked) or not ours
            return None
        del self.in_flight[r.transaction]
        if r.status == Status.SUCCESS:
            self.counters.acked += 1
        else:
            self.counters.errors += 1
        return r.transaction, r.status

    def expire(self, now: int) -> tuple[list[bytes], list[int]]:
        """(datagrams to resend, transaction ids given up) for the writes whose timeout passed."""
        resend, failed = [], []
        for tid, f in list(self.in_flight.items()):
            if now - f.sent_at < self.timeout_ns:
                continue
            if f.tries > self.retries:
                del self.in_flight[tid]
                failed.append(tid)
                self.counters.failed += 1
            else:
                f.tries += 1
                f.sent_at = now
                resend.append(f.datagram)
                self.counters.retries += 1
        return resend, failed

    def next_timeout(self) -> int | None:
        return min((f.sent_at + self.timeout_ns for f in self.in_flight.values()), default=None)
