"""The real-time interface's state message (30003), sans IO: byte by byte, at the offsets of UR's
client interface document (RealTime 5.10) and as python-urx's URRTMonitor unpacks it."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from cell.robot.arm import arm_model
from cell.ur import realtime
from cell.ur.arm import RuntimeState, SafetyMode, URArm

Q = np.array([0.1, -1.5, 1.4, -1.6, -1.5, 0.2])
QD = np.array([0.05, 0.0, -0.02, 0.0, 0.0, 0.01])


def arm() -> URArm:
    ur = URArm("r1", arm_model("ur5e"))
    ur.update(Q, QD, np.zeros(6), 12.5)
    return ur


def test_1220_bytes_that_say_so_with_each_field_at_the_documents_offset() -> None:
    st = arm()
    st.digital_out, st.payload, st.cog = 0b101, 1.5, (0.0, 0.01, 0.05)
    m = realtime.encode(st.values)
    assert len(m) == 1220 and m[:4] == struct.pack(">i", 1220)

    def at(offset: int, n: int = 1) -> tuple[float, ...]:
        return struct.unpack_from(f">{n}d", m, offset)

    # the document's offsets (Message Size 4 bytes, Time 8, then the 6-vectors of 48)
    assert at(4) == (12.5,)
    assert at(12, 6) == tuple(Q) and at(252, 6) == tuple(Q)  # q target, q actual
    assert at(300, 6) == tuple(QD)  # qd actual
    assert np.allclose(at(444, 6), st.values("actual_TCP_pose"))  # tool vector actual
    assert at(756) == (7.0,)  # robot mode: RUNNING
    assert at(764, 6) == (253.0,) * 6  # joint modes: RUNNING
    assert at(812) == (float(SafetyMode.NORMAL),)
    assert at(1044) == (5.0,)  # digital outputs, bits as a double
    assert at(1052) == (float(RuntimeState.PLAYING),)  # program state
    assert at(1108) == (float(SafetyMode.NORMAL),)  # safety status
    assert at(1140) == (1.5,) and at(1148, 3) == (0.0, 0.01, 0.05)  # payload mass and CoG
    assert realtime.OFFSET["payload_inertia"] == 1172 and realtime.OFFSET["elbow_position"] == 1060


def test_decoded_by_name_and_by_python_urxs_own_layout() -> None:
    st = arm()
    m = realtime.encode(st.values)
    d = realtime.decode(m)
    assert d["q_actual"] == tuple(Q) and d["qd_actual"] == tuple(QD) and d["time"] == (12.5,)
    assert d["reserved_1"] == (0.0,) * 6
    # urx.urrtmon.URRTMonitor unpacks the body with its struct for controllers of >= 692 bytes and
    # takes q actual at 31:37, the TCP force at 67:73 and the tool vector (target) at 73:79
    urx = struct.Struct(">d6d6d6d6d6d6d6d6d18d6d6d6dQ")
    unp = urx.unpack(m[4 : 4 + urx.size])
    assert unp[31:37] == tuple(Q) and np.allclose(unp[73:79], st.values("target_TCP_pose"))


def test_a_wrong_message_or_field_width_is_refused_with_the_reason() -> None:
    st = arm()
    m = realtime.encode(st.values)
    with pytest.raises(ValueError, match="1220 bytes, not 1219"):
        realtime.decode(m[:-1])
    with pytest.raises(ValueError, match="says it has 1108"):
        realtime.decode(struct.pack(">i", 1108) + m[4:])
    with pytest.raises(ValueError, match="actual_q has 5 values"):
        realtime.encode(lambda f: st.values(f)[:5] if f == "actual_q" else st.values(f))


def test_split_takes_whole_messages_and_keeps_a_part() -> None:
    m = realtime.encode(arm().values)
    buf = bytearray(m + m + m[:100])
    assert realtime.split(buf) == [m, m] and bytes(buf) == m[:100]
