"""The bus envelope, byte by byte (docs/protocols/bus.md)."""

from __future__ import annotations

import random
import struct

import numpy as np
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
    put_arrays,
)
from cell.v1 import bus_pb2, health_pb2, robot_pb2


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
    assert g.observe(1, "a", 9) == 0  # a jump: held until the stream says whether it was its own
    assert g.observe(1, "a", 10) == 2  # it goes on from 9: 7 and 8 were lost
    assert g.observe(1, "b", 0) == 0  # another topic is another stream
    assert g.observe(2, "a", 0) == 0  # a restarted publisher has a new instance
    assert g.observe(1, "a", 4) == 0  # behind the stream: reordered (a duplicate, a replay), not lost
    assert g.observe(1, "a", 11) == 0  # ... and the stream was not moved back by it
    assert (g.lost, g.reordered, g.implausible) == (2, 1, 0)


def test_forged_and_replayed_sequence_numbers_cannot_inflate_the_loss_count() -> None:
    """What `cell fuzz` did to every service's bus.lost (6.6e19): forged envelopes on real streams."""
    g = GapCounter()
    for seq in range(100):
        g.observe(7, "truth/r1", seq)
    g.observe(7, "truth/r1", 2**64 - 1)  # never believed: beyond any queue's loss
    g.observe(7, "truth/r1", 150)  # held, then refuted: the stream goes on from 100
    g.observe(7, "truth/r1", 100)
    g.observe(7, "truth/r1", 40)  # a replay
    g.observe(7, "truth/r1", 101)
    assert (g.lost, g.reordered, g.implausible) == (0, 1, 2)
    # random forgeries into a stream that really loses bursts: the count stays within the forgeries
    rng = random.Random(35)
    for _trial in range(50):
        g, real_lost, forged, seq = GapCounter(), 0, 0, 0
        for _ in range(2000):
            if rng.random() < 0.02:
                burst = rng.randint(1, 50)
                seq += burst
                real_lost += burst
            g.observe(1, "t", seq)
            seq += 1
            if rng.random() < 0.05:
                forged += 1
                g.observe(1, "t", rng.choice([rng.getrandbits(64), seq + rng.randint(-30, 30)]))
        g.observe(1, "t", seq)  # (the last jump confirmed)
        assert real_lost - forged <= g.lost <= real_lost + forged, (g.lost, real_lost, forged)
    # forged publisher instances cannot fill memory: the least recently heard streams are forgotten
    g = GapCounter()
    for instance in range(3 * GapCounter.MAX_STREAMS):
        g.observe(instance, "x", 0)
    g.observe(0, "y", 0)
    assert len(g._next) == GapCounter.MAX_STREAMS


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


def test_arrays_go_into_packed_fields_byte_for_byte_as_lists_do() -> None:
    """put_arrays writes a fleet's joints through their wire bytes: the message must be the one built
    from lists, byte for byte, and a field it cannot fill so is refused, not half-filled."""
    rng = np.random.default_rng(7)
    q, stopped = rng.normal(size=(300, 6)), rng.random(300) > 0.5
    ids = np.arange(1, 301, dtype=np.uint32)
    by_list = robot_pb2.GroupTruth(t_ns=5, joints=6, robot_id=ids.tolist(), q=q.ravel().tolist(),
                                   stopped=stopped.tolist())  # fmt: skip
    by_array = robot_pb2.GroupTruth(t_ns=5, joints=6, robot_id=ids.tolist())
    put_arrays(by_array, q=q.ravel(), stopped=stopped)
    assert by_array.SerializeToString() == by_list.SerializeToString()
    with pytest.raises(TypeError, match="robot_id is not a repeated field of fixed width"):
        put_arrays(by_array, q=q.ravel(), robot_id=ids)
    assert by_array.SerializeToString() == by_list.SerializeToString()
