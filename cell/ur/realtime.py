"""The real-time client interface's state message (30003), sans IO.

An e-Series controller sends each client of port 30003 its state every control step (500 Hz), as one
message: int32 length (itself included), then doubles, big-endian, in the order of UR's client
interface document "RealTime 5.10" (1220 bytes); integers and bit sets are sent as doubles too.  UR
deprecated this interface for RTDE, but lab scripts and python-urx's URRTMonitor still read it.

Each field here names the RTDE output field it carries (cell.ur.fields), so the two interfaces show
the same truth of the same tick; None is a slot UR reserves for its own software (zeros).
"""

from __future__ import annotations

import struct
from collections.abc import Callable

# (the document's name for it, how many doubles, the RTDE output field it carries or None)
LAYOUT: tuple[tuple[str, int, str | None], ...] = (
    ("time", 1, "timestamp"),
    ("q_target", 6, "target_q"),
    ("qd_target", 6, "target_qd"),
    ("qdd_target", 6, "target_qdd"),
    ("i_target", 6, "target_current"),
    ("m_target", 6, "target_moment"),
    ("q_actual", 6, "actual_q"),
    ("qd_actual", 6, "actual_qd"),
    ("i_actual", 6, "actual_current"),
    ("i_control", 6, "joint_control_output"),
    ("tool_vector_actual", 6, "actual_TCP_pose"),
    ("tcp_speed_actual", 6, "actual_TCP_speed"),
    ("tcp_force", 6, "actual_TCP_force"),
    ("tool_vector_target", 6, "target_TCP_pose"),
    ("tcp_speed_target", 6, "target_TCP_speed"),
    ("digital_input_bits", 1, "actual_digital_input_bits"),
    ("motor_temperatures", 6, "joint_temperatures"),
    ("controller_timer", 1, "actual_execution_time"),
    ("test_value", 1, None),
    ("robot_mode", 1, "robot_mode"),
    ("joint_modes", 6, "joint_mode"),
    ("safety_mode", 1, "safety_mode"),
    ("reserved_1", 6, None),
    ("tool_accelerometer_values", 3, "actual_tool_accelerometer"),
    ("reserved_2", 6, None),
    ("speed_scaling", 1, "speed_scaling"),
    ("linear_momentum_norm", 1, "actual_momentum"),
    ("software_only", 1, None),
    ("software_only_2", 1, None),
    ("v_main", 1, "actual_main_voltage"),
    ("v_robot", 1, "actual_robot_voltage"),
    ("i_robot", 1, "actual_robot_current"),
    ("v_actual", 6, "actual_joint_voltage"),
    ("digital_outputs", 1, "actual_digital_output_bits"),
    ("program_state", 1, "runtime_state"),
    ("elbow_position", 3, "elbow_position"),
    ("elbow_velocity", 3, "elbow_velocity"),
    ("safety_status", 1, "safety_status"),
    ("reserved_3", 3, None),
    ("payload_mass", 1, "payload"),
    ("payload_cog", 3, "payload_cog"),
    ("payload_inertia", 6, "payload_inertia"),
)
DOUBLES = sum(n for _, n, _ in LAYOUT)
SIZE = 4 + 8 * DOUBLES  # 1220: RealTime 5.10's message size
_MESSAGE = struct.Struct(f">i{DOUBLES}d")
# where each field starts, in bytes from the message's start (the document's offsets)
OFFSET = {name: 4 + 8 * sum(n for _, n, _ in LAYOUT[:i]) for i, (name, _, _) in enumerate(LAYOUT)}

Values = Callable[[str], tuple]  # an RTDE output field's values now (URArm.values)


def encode(values: Values) -> bytes:
    """One state message from the arm's RTDE output fields (this tick's)."""
    flat: list[float] = []
    for _name, n, field in LAYOUT:
        if field is None:
            flat.extend([0.0] * n)
        else:
            got = values(field)
            if len(got) != n:
                raise ValueError(f"RTDE field {field} has {len(got)} values, the real-time message {n}")
            flat.extend(float(v) for v in got)
    return _MESSAGE.pack(SIZE, *flat)


def decode(message: bytes) -> dict[str, tuple[float, ...]]:
    """A state message's fields by the document's names (for clients and tests)."""
    if len(message) != SIZE:
        raise ValueError(f"a RealTime 5.10 message has {SIZE} bytes, not {len(message)}")
    size, *flat = _MESSAGE.unpack(message)
    if size != SIZE:
        raise ValueError(f"the message says it has {size} bytes, not {SIZE}")
    out: dict[str, tuple[float, ...]] = {}
    i = 0
    for name, n, _ in LAYOUT:
        out[name] = tuple(flat[i : i + n])
        i += n
    return out


def split(buf: bytearray) -> list[bytes]:
    """Whole messages off the front of buf (removed from it)."""
    out = []
    while len(buf) >= 4:
        (size,) = struct.unpack_from(">i", buf)
        if size < 4 or size > len(buf):
            break
        out.append(bytes(buf[:size]))
        del buf[:size]
    return out
