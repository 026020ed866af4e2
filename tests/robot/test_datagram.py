"""The robot datagram codec, byte by byte (docs/protocols/robot-datagram.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cell.robot import datagram
from cell.robot.datagram import SCALE, Datagram, DatagramError, Kind, Reject


def test_scale_is_the_prototypes() -> None:
    assert pytest.approx(1.0680707e7, rel=1e-7) == SCALE
    assert pytest.approx(9.36e-8, rel=1e-3) == 1 / SCALE


def test_status_bytes_are_exact() -> None:
    d = Datagram(
        robot_id=0x0102, joint_id=5, kind=Kind.STATUS, seq=0x0A0B0C0D, velocity=1.0, position=-math.pi
    )
    raw = datagram.encode(d)
    v, p = round(1.0 * SCALE), round(-math.pi * SCALE)
    expected = (
        bytes.fromhex("0102")  # robot_id
        + bytes([5, 0])  # joint, kind=status
        + bytes.fromhex("0a0b0c0d")  # seq
        + v.to_bytes(8, "big", signed=True)
        + p.to_bytes(8, "big", signed=True)
    )
    assert raw == expected
    assert len(raw) == 24
    # 1 rad/s = (2^31 - 1) / (64 pi) = 10,680,707.4 -> 10,680,707 units = 0x00a2f983, big-endian
    assert raw[8:16] == bytes.fromhex("0000000000a2f983")
    # -pi rad = -(2^31 - 1) / 64 = -33,554,431.98 -> -33,554,432 = 0xfffffffffe000000
    assert raw[16:24] == bytes.fromhex("fffffffffe000000")


def test_command_round_trip_within_one_unit() -> None:
    d = Datagram(7, 3, Kind.COMMAND, 99, velocity=-0.123456789, position=2.5)
    back = datagram.decode(datagram.encode(d), kind=Kind.COMMAND, robot_id=7, joints=6)
    assert (back.robot_id, back.joint_id, back.kind, back.seq) == (7, 3, Kind.COMMAND, 99)
    assert abs(back.velocity - d.velocity) <= 0.5 / SCALE
    assert abs(back.position - d.position) <= 0.5 / SCALE


def test_limits_of_the_fields() -> None:
    d = Datagram(0xFFFF, 255, Kind.COMMAND, 0xFFFFFFFF, velocity=-1e6, position=1e6)
    back = datagram.decode(datagram.encode(d))
    assert (back.robot_id, back.joint_id, back.seq) == (0xFFFF, 255, 0xFFFFFFFF)
    assert back.position == pytest.approx(1e6, abs=1 / SCALE)
    for bad in (math.nan, math.inf, 1e12):
        with pytest.raises(ValueError, match="cannot be carried"):
            datagram.encode(Datagram(1, 0, Kind.STATUS, 0, bad, 0.0))


def _raw(robot=1, joint=0, kind=1, seq=0) -> bytes:
    return robot.to_bytes(2, "big") + bytes([joint, kind]) + seq.to_bytes(4, "big") + bytes(16)


@pytest.mark.parametrize(
    ("data", "expect", "reason"),
    [
        (b"", {}, Reject.LENGTH),
        (_raw()[:23], {}, Reject.LENGTH),
        (_raw() + b"\0", {}, Reject.LENGTH),
        (_raw(kind=2), {}, Reject.KIND),
        (_raw(kind=0), {"kind": Kind.COMMAND}, Reject.KIND),
        (_raw(robot=2), {"robot_id": 1}, Reject.ROBOT),
        (_raw(joint=6), {"joints": 6}, Reject.JOINT),
    ],
)
def test_rejects_with_a_reason(data: bytes, expect: dict, reason: Reject) -> None:
    with pytest.raises(DatagramError) as info:
        datagram.decode(data, **expect)
    assert info.value.reason is reason


def test_batch_codec_matches_scalar() -> None:
    rng = np.random.default_rng(1)
    n = 50
    v, p = rng.uniform(-3, 3, n), rng.uniform(-6, 6, n)
    recs = datagram.empty(n)
    datagram.pack(
        recs,
        robot_id=np.arange(n) + 1,
        joint_id=np.arange(n) % 6,
        kind=Kind.STATUS,
        seq=7,
        velocity=v,
        position=p,
    )
    raw = recs.tobytes()
    assert len(raw) == 24 * n
    for i in range(n):
        one = Datagram(i + 1, i % 6, Kind.STATUS, 7, float(v[i]), float(p[i]))
        assert raw[24 * i : 24 * (i + 1)] == datagram.encode(one)
    back = datagram.view(raw)
    assert np.array_equal(back["robot_id"], np.arange(n) + 1)
    assert np.allclose(datagram.velocities(back), v, atol=0.5 / SCALE)
    assert np.allclose(datagram.positions(back), p, atol=0.5 / SCALE)
    with pytest.raises(ValueError, match="whole number"):
        datagram.view(raw[:-1])


@given(st.binary(max_size=40))
def test_decode_never_fails_any_other_way(data: bytes) -> None:
    try:
        d = datagram.decode(data)
    except DatagramError:
        return
    assert len(data) == 24 and d.kind in (Kind.STATUS, Kind.COMMAND)
