"""The bus envelope: the fixed binary header every bus message carries (docs/protocols/bus.md).

Sans-IO: this module turns (topic, header, payload) into ZeroMQ frames and back,
and counts lost messages; it never touches a socket.  The header is a packed
struct rather than a protobuf message because it rides on every message and
must cost well under a microsecond; payloads are protobuf.
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

from google.protobuf import descriptor_pool, message_factory
from google.protobuf.message import DecodeError, Message

VERSION = 1
# version u8, kind u8, source length u8, type-name length u8, instance u32,
# seq u64, send time u64 (CLOCK_MONOTONIC ns), correlation id u64; then source, then type name
HEADER = struct.Struct("!BBBBIQQQ")
MAX_NAME = 255
# topics are '/'-separated words; a leading '_' is reserved for the bus's own traffic
M = TypeVar("M", bound="Message")
_TOPIC = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*(/[A-Za-z0-9_.\-]+)*/?")


class Kind(IntEnum):
    PUBLISH = 0
    REQUEST = 1
    REPLY = 2
    ERROR = 3


class EnvelopeError(ValueError):
    """A frame set that is not a well-formed bus message."""


@dataclass(slots=True)
class Header:
    kind: Kind
    source: str
    type_name: str
    instance: int
    seq: int
    sent_ns: int
    correlation: int


@dataclass(slots=True)
class Envelope:
    """One received bus message; the payload is decoded only when asked for."""

    topic: str
    header: Header
    payload: bytes

    def message(self) -> Message:
        """The payload as the protobuf type its header names (the module defining it must be imported)."""
        return self.decode(message_class(self.header.type_name))

    def decode(self, cls: type[M]) -> M:
        msg = cls()
        try:
            msg.ParseFromString(self.payload)
        except DecodeError as exc:
            raise EnvelopeError(
                f"payload on {self.topic!r} is not a valid {cls.DESCRIPTOR.full_name}"
            ) from exc
        return msg


def check_topic(topic: str) -> bytes:
    """Validate a topic or prefix and return it encoded ('_'-topics are the bus's own)."""
    if not _TOPIC.fullmatch(topic):
        raise ValueError(
            f"bad bus topic {topic!r}: use '/'-separated words of letters, digits, '_', '.', '-'"
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
            raise EnvelopeError(
                f"unknown message type {type_name!r} (is its _pb2 module imported?)"
            ) from None
        cls = _classes[type_name] = message_factory.GetMessageClass(desc)
    return cls


class Encoder:
    """One publisher's side of the envelope: its identity and per-topic sequence numbers.

    Sequence numbers count per (publisher, topic) so that a subscriber that
    filters by prefix can still tell a lost message from one it never asked for.
    """

    def __init__(
        self, source: str, instance: int | None = None, clock: Callable[[], int] = time.monotonic_ns
    ) -> None:
        self.source = source
        self._clock = clock
        self._source = source.encode()
        if not 0 < len(self._source) <= MAX_NAME:
            raise ValueError(f"bus source name must be 1..{MAX_NAME} bytes, got {source!r}")
        self.instance = instance if instance is not None else int.from_bytes(os.urandom(4), "big")
        self._seq: dict[bytes, int] = {}
        self._types: dict[str, bytes] = {}

    def encode(
        self,
        topic: bytes,
        type_name: str,
        payload: bytes,
        kind: Kind = Kind.PUBLISH,
        correlation: int = 0,
    ) -> list[bytes]:
        """The frames [topic, header+payload] of one message; topic must come from check_topic()."""
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        tname = self._types.get(type_name)
        if tname is None:
            tname = type_name.encode()
            if len(tname) > MAX_NAME:
                raise ValueError(f"message type name too long: {type_name!r}")
            self._types[type_name] = tname
        head = HEADER.pack(
            VERSION, kind, len(self._source), len(tname), self.instance, seq, self._clock(), correlation
        )
        return [topic, head + self._source + tname + payload]


_names: dict[bytes, str] = {}


def _name(raw: bytes) -> str:
    s = _names.get(raw)
    if s is None:
        s = raw.decode()  # UnicodeDecodeError is a ValueError: caught by decode()
        if len(_names) < 4096:
            _names[raw] = s
    return s


def decode(frames: list[bytes]) -> Envelope:
    """Parse the frames of one message; raise EnvelopeError with the reason if malformed."""
    if len(frames) != 2:
        raise EnvelopeError(f"expected 2 frames, got {len(frames)}")
    topic, body = frames
    if len(body) < HEADER.size:
        raise EnvelopeError(f"header too short: {len(body)} bytes < {HEADER.size}")
    version, kind, nsrc, ntype, instance, seq, sent_ns, corr = HEADER.unpack_from(body)
    if version != VERSION:
        raise EnvelopeError(f"unsupported envelope version {version}")
    if kind > Kind.ERROR:
        raise EnvelopeError(f"unknown message kind {kind}")
    start = HEADER.size + nsrc + ntype
    if len(body) < start:
        raise EnvelopeError(f"header names overrun the frame ({len(body)} bytes < {start})")
    try:
        header = Header(
            Kind(kind),
            _name(body[HEADER.size : HEADER.size + nsrc]),
            _name(body[HEADER.size + nsrc : start]),
            instance,
            seq,
            sent_ns,
            corr,
        )
        return Envelope(_name(topic), header, body[start:])
    except UnicodeDecodeError as exc:
        raise EnvelopeError(f"topic or names are not UTF-8: {exc.reason}") from None


class GapCounter:
    """Counts messages lost on the way from publishers to one subscriber.

    A jump in a (publisher instance, topic) sequence adds the missing count to
    `lost`; a sequence that goes backwards is counted as `reordered` and restarts
    tracking from there.  A restarted publisher has a new instance id, so its
    fresh sequence starts a new stream instead of looking like a loss.
    """

    __slots__ = ("_next", "lost", "reordered")

    def __init__(self) -> None:
        self._next: dict[tuple[int, str], int] = {}
        self.lost = 0
        self.reordered = 0

    def observe(self, instance: int, topic: str, seq: int) -> int:
        """Record one message; return how many messages were lost just before it."""
        key = (instance, topic)
        expected = self._next.get(key)
        self._next[key] = seq + 1
        if expected is None or seq == expected:
            return 0
        if seq > expected:
            gap = seq - expected
            self.lost += gap
            return gap
        self.reordered += 1
        return 0
