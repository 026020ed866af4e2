"""The bus envelope, byte by byte (docs/protocols/bus.md)."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cell.bus.envelope import (
    HEADER,
    Encoder,
    EnvelopeError,
    GapCounter,
    Kind,
    check_topic,
    decode,
    message_class,
)
from cell.v1 import bus_pb2, health_pb2


def fixed_encoder() -> Encoder:
    return Encoder("svc", instance=0x01020304, clock=lambda: 0x1122334455667788)


def test_header_bytes_are_exact() -> None:
    frame = fixed_encoder().encode(b"a/b", "cell.v1.Empty", b"\x08\x01", Kind.REQUEST, correlation=7)
    expected = (
        b"a/b\0"  # topic first, so ZeroMQ's prefix filter sees it
        + bytes([1, 1, 3, 13])  # version, kind=REQUEST, len("svc"), len("cell.v1.Empty")
        + bytes.fromhex("01020304")  # instance
        + (0).to_bytes(8, "big")  # seq: first on this topic
        + bytes.fromhex("1122334455667788")  # send time
        + (7).to_bytes(8, "big")  # correlation
        + b"svc"
        + b"cell.v1.Empty"
        + b"\x08\x01"
    )
    assert frame == expected
    assert HEADER.size == 32


def test_sequence_counts_per_topic() -> None:
    enc = fixed_encoder()
    seqs = [decode(enc.encode(t, "x.Y", b"")).seq for t in (b"a", b"a", b"b", b"a", b"b")]
    assert seqs == [0, 1, 0, 2, 1]


def test_round_trip_with_payload() -> None:
    hb = health_pb2.Heartbeat(service="bus", pid=42, counters={"x": 1.5})
    enc = fixed_encoder()
    env = decode(enc.encode(b"health/bus", hb.DESCRIPTOR.full_name, hb.SerializeToString()))
    assert env.topic == "health/bus"
    assert env.kind is Kind.PUBLISH
    assert env.source == "svc"
    assert env.instance == 0x01020304
    assert env.sent_ns == 0x1122334455667788
    assert env.message() == hb
    assert env.decode(health_pb2.Heartbeat).counters["x"] == 1.5


def _frame(topic=b"t", version=1, kind=0, nsrc=1, ntype=1, names=b"ab", payload=b"") -> bytes:
    return topic + b"\0" + struct.pack("!BBBBIQQQ", version, kind, nsrc, ntype, 1, 2, 3, 4) + names + payload


def test_well_formed_test_frame() -> None:
    env = decode(_frame(payload=b"xyz"))
    assert (env.topic, env.source, env.type_name, env.seq, env.payload) == ("t", "a", "b", 2, b"xyz")


@pytest.mark.parametrize(
    ("frame", "reason"),
    [
        (b"", "no topic"),
        (b"t", "no topic"),
        (_frame(topic=b""), "no topic"),
        (b"x" * 300 + b"\0" + _frame()[2:], "no topic"),  # topics are at most 255 bytes
        (b"t\0" + b"\x01" * 31, "header too short"),
        (_frame(version=2), "unsupported envelope version 2"),
        (_frame(kind=9), "unknown message kind 9"),
        (_frame(nsrc=200), "overrun"),
        (_frame(names=b"\xff\xfe"), "not UTF-8"),
        (_frame(topic=b"\xff"), "not UTF-8"),
    ],
)
def test_malformed_frames_are_rejected_with_a_reason(frame: bytes, reason: str) -> None:
    with pytest.raises(EnvelopeError, match=reason):
        decode(frame)


def test_undecodable_payload_is_an_envelope_error() -> None:
    env = decode(fixed_encoder().encode(b"t", "cell.v1.RpcError", b"\x0a\xff"))  # length overruns
    with pytest.raises(EnvelopeError, match=r"not a valid cell\.v1\.RpcError"):
        env.message()


def test_unknown_type_name_is_an_envelope_error() -> None:
    with pytest.raises(EnvelopeError, match="unknown message type"):
        message_class("no.such.Type")
    assert message_class("cell.v1.BenchPayload") is type(bus_pb2.BenchPayload())


def test_gap_counter() -> None:
    g = GapCounter()
    assert g.observe(1, "a", 5) == 0  # joining late is not a loss
    assert g.observe(1, "a", 6) == 0
    assert g.observe(1, "a", 9) == 2  # 7 and 8 lost
    assert g.observe(1, "b", 0) == 0  # another topic is another stream
    assert g.observe(2, "a", 0) == 0  # a restarted publisher has a new instance
    assert g.observe(1, "a", 4) == 0  # backwards: reordered, not lost
    assert (g.lost, g.reordered) == (2, 1)
    assert g.observe(1, "a", 5) == 0  # tracking restarted from 4


@pytest.mark.parametrize("topic", ["status/r1", "a", "dataplane/counters", "events/service/bus", "x-y.z_1/"])
def test_good_topics(topic: str) -> None:
    assert check_topic(topic) == topic.encode()


@pytest.mark.parametrize("topic", ["", "/a", "a//b", "_sync/x", "a b", "é", "a/\x00", "a" * 256])
def test_bad_topics(topic: str) -> None:
    with pytest.raises(ValueError, match="bad bus topic"):
        check_topic(topic)


@given(st.binary(max_size=400))
def test_decode_never_fails_any_other_way(frame: bytes) -> None:
    try:
        env = decode(frame)
    except EnvelopeError:
        return
    assert frame.startswith(env.topic.encode() + b"\0")


@given(
    topic=st.from_regex(r"[a-z][a-z0-9_]{0,20}(/[a-z0-9_.\-]{1,10}){0,4}", fullmatch=True),
    source=st.text(min_size=1, max_size=60),
    payload=st.binary(max_size=300),
    kind=st.sampled_from(list(Kind)),
    correlation=st.integers(0, 2**64 - 1),
)
def test_encode_decode_round_trip(
    topic: str, source: str, payload: bytes, kind: Kind, correlation: int
) -> None:
    enc = Encoder(source, instance=99, clock=lambda: 123)
    env = decode(enc.encode(check_topic(topic), "cell.v1.BenchPayload", payload, kind, correlation))
    assert (env.topic, env.source, env.kind, env.correlation, env.payload) == (
        topic,
        source,
        kind,
        correlation,
        payload,
    )
    assert (env.instance, env.seq, env.sent_ns, env.type_name) == (99, 0, 123, "cell.v1.BenchPayload")
