"""The bus envelope: how one bus message is laid out in one ZeroMQ frame (docs/protocols/bus.md).

    topic NUL | header (32 bytes) | source | type name | payload (protobuf)

Sans-IO: this module turns a message into its frame and back, and counts lost
messages; it never touches a socket.  One frame, because pyzmq's multipart
calls cost ten times a single send/recv; the topic comes first so that
ZeroMQ's prefix filtering works as usual.  The header is a packed struct, not
protobuf, because it rides on every message and must cost well under a
microsecond.
"""

from __future__ import annotations

import os
import re
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import TypeVar

import numpy as np
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import DecodeError, Message

VERSION = 1
# version u8, kind u8, source length u8, type-name length u8, instance u32,
# seq u64, send time u64 (CLOCK_MONOTONIC ns), correlation id u64
HEADER = struct.Struct("!BBBBIQQQ")
_HSIZE = HEADER.size
_unpack = HEADER.unpack_from
MAX_NAME = 255
MAX_TOPIC = 255
M = TypeVar("M", bound="Message")
# topics are '/'-separated words; a leading '_' is reserved for the bus's own traffic
_TOPIC = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*(/[A-Za-z0-9_.\-]+)*/?")


class Kind(IntEnum):
    PUBLISH = 0
    REQUEST = 1
    REPLY = 2
    ERROR = 3


_KINDS = tuple(Kind)


class EnvelopeError(ValueError):
    """A frame that is not a well-formed bus message."""


@dataclass(slots=True)
class Envelope:
    """One received bus message: topic, header fields and payload (decoded only when asked for)."""

    topic: str
    kind: Kind
    source: str
    type_name: str
    instance: int  # random per publishing node: a restarted node is a new stream
    seq: int  # per (instance, topic)
    sent_ns: int  # CLOCK_MONOTONIC of the sender
    correlation: int  # request/reply matching; 0 on plain publishes
    payload: bytes

    def message(self) -> Message:
        """The payload as the protobuf type its header names (the module defining it must be imported)."""
        return self.decode(message_class(self.type_name))

    def decode(self, cls: type[M]) -> M:
        msg = cls()
        try:
            msg.ParseFromString(self.payload)
        except DecodeError as exc:
            what = cls.DESCRIPTOR.full_name
            raise EnvelopeError(f"payload on {self.topic!r} is not a valid {what}") from exc
        return msg


def check_topic(topic: str) -> bytes:
    """Validate a topic or prefix and return it encoded ('_'-topics are the bus's own)."""
    if not _TOPIC.fullmatch(topic) or len(topic) > MAX_TOPIC:
        raise ValueError(
            f"bad bus topic {topic!r}: use up to {MAX_TOPIC} bytes of '/'-separated words "
            "of letters, digits, '_', '.', '-'"
        )
    return topic.encode()


_classes: dict[str, type[Message]] = {}


def message_class(type_name: str) -> type[Message]:
    """The generated class for a protobuf full name, from the default descriptor pool."""
    cls = _classes.get(type_name)
    if cls is None:
        try:
            desc = descriptor_pool.Default().FindMessageTypeByName(type_name)
        except KeyError:
            why = f"unknown message type {type_name!r} (is its _pb2 module imported?)"
            raise EnvelopeError(why) from None
        cls = _classes[type_name] = message_factory.GetMessageClass(desc)
    return cls


# the fixed-width scalar kinds a packed repeated field holds as plain little-endian arrays
_FIXED = {
    FieldDescriptor.TYPE_DOUBLE: "<f8",
    FieldDescriptor.TYPE_FLOAT: "<f4",
    FieldDescriptor.TYPE_BOOL: "u1",
    FieldDescriptor.TYPE_FIXED32: "<u4",
    FieldDescriptor.TYPE_FIXED64: "<u8",
    FieldDescriptor.TYPE_SFIXED32: "<i4",
    FieldDescriptor.TYPE_SFIXED64: "<i8",
}


def put_arrays(msg: Message, **arrays: np.ndarray) -> None:
    """Append numpy arrays to `msg`'s packed repeated fields of fixed width (double, float, bool,
    fixed) through their wire bytes, which protobuf parses at memory speed: a fleet's thousands of
    joint values go in ten times faster than from a list (`extend`, `tolist()`)."""
    out = []
    for name, values in arrays.items():
        field = msg.DESCRIPTOR.fields_by_name[name]
        dtype = _FIXED.get(field.type)
        if dtype is None or not field.is_repeated:
            raise TypeError(f"{msg.DESCRIPTOR.name}.{name} is not a repeated field of fixed width")
        raw = np.ascontiguousarray(values, dtype=dtype).tobytes()
        out += [_varint(field.number << 3 | 2), _varint(len(raw)), raw]
    msg.MergeFromString(b"".join(out))


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append(n & 0x7F | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


class Encoder:
    """One publisher's side of the envelope: its identity and per-topic sequence numbers.

    Sequence numbers count per (publisher, topic) so that a subscriber that
    filters by prefix can still tell a lost message from one it never asked for.
    """

    def __init__(
        self, source: str, instance: int | None = None, clock: Callable[[], int] = time.monotonic_ns
    ) -> None:
        self.source = source
        self._source = source.encode()
        if not 0 < len(self._source) <= MAX_NAME:
            raise ValueError(f"bus source name must be 1..{MAX_NAME} bytes, got {source!r}")
        self.instance = instance if instance is not None else int.from_bytes(os.urandom(4), "big")
        self._clock = clock
        self._seq: dict[bytes, int] = {}
        self._names: dict[str, tuple[int, bytes]] = {}  # type name -> (its length, source + type name)

    def encode(
        self,
        topic: bytes,
        type_name: str,
        payload: bytes,
        kind: Kind = Kind.PUBLISH,
        correlation: int = 0,
    ) -> bytes:
        """The frame of one message; topic must come from check_topic() (or be the bus's own)."""
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        names = self._names.get(type_name)
        if names is None:
            tname = type_name.encode()
            if len(tname) > MAX_NAME:
                raise ValueError(f"message type name too long: {type_name!r}")
            names = self._names[type_name] = (len(tname), self._source + tname)
        head = HEADER.pack(
            VERSION, kind, len(self._source), names[0], self.instance, seq, self._clock(), correlation
        )
        return b"".join((topic, b"\0", head, names[1], payload))


_names: dict[bytes, str] = {}


def _name(raw: bytes) -> str:
    s = _names.get(raw)
    if s is None:
        s = raw.decode()  # UnicodeDecodeError is a ValueError: caught by decode()
        if len(_names) < 4096:
            _names[raw] = s
    return s


def frame_topic(frame: bytes) -> bytes:
    """The topic of a frame without decoding the rest (b'' if it has none)."""
    end = frame.find(b"\0", 0, MAX_TOPIC + 1)
    return frame[:end] if end > 0 else b""


def decode(frame: bytes) -> Envelope:
    """Parse one frame; raise EnvelopeError with the reason if it is not a well-formed message."""
    end = frame.find(b"\0", 0, MAX_TOPIC + 1)
    if end <= 0:
        raise EnvelopeError("no topic: expected 'topic NUL header ...'")
    h = end + 1
    if len(frame) < h + _HSIZE:
        raise EnvelopeError(f"header too short: {len(frame) - h} bytes < {_HSIZE}")
    version, kind, nsrc, ntype, instance, seq, sent_ns, corr = _unpack(frame, h)
    if version != VERSION:
        raise EnvelopeError(f"unsupported envelope version {version}")
    if kind >= len(_KINDS):
        raise EnvelopeError(f"unknown message kind {kind}")
    src = h + _HSIZE
    mid = src + nsrc
    start = mid + ntype
    if len(frame) < start:
        raise EnvelopeError(f"header names overrun the frame ({len(frame)} bytes < {start})")
    try:
        return Envelope(
            _name(frame[:end]),
            _KINDS[kind],
            _name(frame[src:mid]),
            _name(frame[mid:start]),
            instance,
            seq,
            sent_ns,
            corr,
            frame[start:],
        )
    except UnicodeDecodeError as exc:
        raise EnvelopeError(f"topic or names are not UTF-8: {exc.reason}") from None


class GapCounter:
    """Counts messages lost on the way from publishers to one subscriber, believing only what a
    stream itself confirms (a forged or replayed envelope on the bus must not make `cell status` lie).

    Each (publisher instance, topic) is a stream of consecutive sequence numbers.  A jump ahead is
    held, not yet counted: the stream's next message confirms it (it is the jump's successor: the
    messages between were lost) or refutes it (anything else: the jump was not the stream's,
    counted `implausible`; a real loss right after a jump is then counted from the next jump).  A
    jump of more than MAX_GAP is never believed, and a sequence number behind the stream is
    `reordered` (a duplicate or a replay) without moving it back.  A restarted publisher has a new
    instance id, so its fresh sequence starts a new stream.  At most MAX_STREAMS streams are
    followed, the least recently heard forgotten first (forged instance ids cannot fill memory).
    """

    MAX_GAP = 1_000_000  # more than any subscriber's queue could have dropped
    MAX_STREAMS = 4096

    __slots__ = ("_jump", "_next", "implausible", "lost", "reordered")

    def __init__(self) -> None:
        self._next: dict[tuple[int, str], int] = {}  # the stream's next sequence number (LRU order)
        self._jump: dict[tuple[int, str], int] = {}  # a jump ahead not yet confirmed: the seq it came with
        self.lost = 0
        self.reordered = 0
        self.implausible = 0

    def observe(self, instance: int, topic: str, seq: int) -> int:
        """Record one message; return how many messages were lost before it (counted once confirmed)."""
        key = (instance, topic)
        nexts = self._next
        expected = nexts.pop(key, None)  # (re-inserted below: most recently heard last)
        if expected is None:  # joining late is not a loss
            if len(nexts) >= self.MAX_STREAMS:
                old = next(iter(nexts))
                del nexts[old]
                self._jump.pop(old, None)
            nexts[key] = seq + 1
            return 0
        if seq == expected:
            nexts[key] = seq + 1
            if self._jump.pop(key, None) is not None:
                self.implausible += 1  # the stream went on from before the jump: not its message
            return 0
        if seq < expected:
            nexts[key] = expected
            self.reordered += 1
            return 0
        jump = self._jump.get(key)
        if jump is not None and seq == jump + 1:  # it goes on from the jump: those between were lost
            del self._jump[key]
            nexts[key] = seq + 1
            gap = jump - expected
            self.lost += gap
            return gap
        nexts[key] = expected
        if jump is not None:  # neither from before the jump nor from it: the jump is not believed
            self.implausible += 1
        if seq - expected > self.MAX_GAP:
            self._jump.pop(key, None)
            self.implausible += 1
        else:
            self._jump[key] = seq
        return 0
