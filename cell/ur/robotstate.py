"""The robot state package of the primary and secondary interfaces (30001, 30002), sans IO.

A PolyScope 5 controller sends each client of these ports its state at 10 Hz: one package of type 16
(int32 length, header included; uint8 type) holding sub-packages, each int32 length (its header
included), uint8 type, then its fields, big-endian, as UR's client interface document (5.x) lays
them out and UR's client library reads them.  Sent here: robot mode data (0), joint data (1), tool
data (2), masterboard data (3), Cartesian info (4), kinematics info (5), configuration data (6),
force mode data (7) and additional info (8).  What the emulator has no model of (currents, voltages,
temperatures, the analog inputs) are fixed, plausible values, as on RTDE.
"""

from __future__ import annotations

import struct
from enum import IntEnum

import numpy as np

from cell.ur.arm import JointMode, RobotMode, RuntimeState, SafetyMode, URArm

ROBOT_STATE = 16
STATE_HZ = 10
_HEADER = struct.Struct(">iB")
# fixed values where the emulator models nothing: joint and board voltages, temperatures, currents
VOLTAGE, TEMPERATURE_C, ROBOT_CURRENT_A = 48.0, 30.0, 0.5
# URScript's defaults for a movej/movel without a and v (rad/s, rad/s^2, m/s, m/s^2), and the
# blend radius it reports
V_JOINT, A_JOINT, V_TOOL, A_TOOL, EQ_RADIUS = 1.05, 1.4, 0.25, 1.2, 0.0
# configuration data: the robot's type (UR3 1, UR5 2, UR10 3, UR16 4, UR20 7, UR30 8) and its series
ROBOT_TYPE = {"ur3e": 1, "ur5e": 2, "ur10e": 3, "ur16e": 4, "ur20": 7, "ur30": 8}
E_SERIES = 3
MASTERBOARD_VERSION, CONTROLLER_BOX = 7, 7


class StateType(IntEnum):
    ROBOT_MODE = 0
    JOINT = 1
    TOOL = 2
    MASTERBOARD = 3
    CARTESIAN = 4
    KINEMATICS = 5
    CONFIGURATION = 6
    FORCE_MODE = 7
    ADDITIONAL = 8


def _sub(kind: StateType, fmt: str, *values: object) -> bytes:
    body = struct.pack(">" + fmt, *values)
    return _HEADER.pack(_HEADER.size + len(body), kind) + body


def robot_mode(st: URArm, t_us: int) -> bytes:
    estop = st.safety_mode in (SafetyMode.SYSTEM_EMERGENCY_STOP, SafetyMode.ROBOT_EMERGENCY_STOP)
    powered = st.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
    return _sub(
        StateType.ROBOT_MODE,
        "Q7?bBdddB",
        t_us,
        True,  # a real robot connected
        True,  # and enabled (not a simulation)
        powered,
        estop,
        st.safety_mode == SafetyMode.PROTECTIVE_STOP,
        st.runtime == RuntimeState.PLAYING,
        st.runtime == RuntimeState.PAUSED,
        int(st.robot_mode),
        0,  # control mode: position
        st.speed_fraction,
        st.speed_fraction if st.can_move else 0.0,
        1.0,  # the target speed fraction's limit
        0,
    )


def joints(arm: URArm) -> bytes:
    mode = JointMode.RUNNING if arm.robot_mode == RobotMode.RUNNING else JointMode.POWER_OFF
    values: list[object] = []
    for j in range(len(arm.q)):
        q, qd = float(arm.q[j]), float(arm.qd[j])
        values += [q, q, qd, 0.0, VOLTAGE, TEMPERATURE_C, TEMPERATURE_C, int(mode)]
    return _sub(StateType.JOINT, "dddffffB" * len(arm.q), *values)


def tool(arm: URArm) -> bytes:
    mode = JointMode.RUNNING if arm.robot_mode == RobotMode.RUNNING else JointMode.POWER_OFF
    return _sub(StateType.TOOL, "bbddfBffB", 0, 0, 0.0, 0.0, VOLTAGE, 0, 0.0, TEMPERATURE_C, int(mode))


def masterboard(arm: URArm) -> bytes:
    return _sub(
        StateType.MASTERBOARD,
        "IIbbddbbddffffB?bIBBB",
        arm.digital_in & 0xFFFFFFFF,
        arm.digital_out & 0xFFFFFFFF,
        0,  # analog input ranges 0, 1
        0,
        0.0,  # analog inputs 0, 1
        0.0,
        0,  # analog output domains 0, 1 (current)
        0,
        float(arm.analog_out[0]),
        float(arm.analog_out[1]),
        TEMPERATURE_C,
        VOLTAGE,
        ROBOT_CURRENT_A,
        0.0,  # the master I/O's current
        int(arm.safety_mode),
        arm.safety_mode == SafetyMode.REDUCED,
        0,  # no Euromap67 interface installed (its four fields then left out)
        0,  # (reserved)
        0,  # the operational mode selector's input
        0,  # the three-position enabling device's input
        0,  # (reserved)
    )


def cartesian(arm: URArm) -> bytes:
    pose = arm.tool.fk(arm.q)
    return _sub(StateType.CARTESIAN, "12d", *pose.tolist(), *arm.tool.tcp.tolist())


def _dh(arm: URArm) -> tuple[list[float], list[float], list[float], list[float]]:
    spec = arm.tool.arm.spec
    n = len(spec.a)
    return [0.0] * n, [float(x) for x in spec.a], [float(x) for x in spec.d], [float(x) for x in spec.alpha]


def kinematics(arm: URArm) -> bytes:
    """The arm's calibration: its nominal DH parameters (theta offsets, a, d, alpha), checksums 0, and
    the calibration status 0 (the robot is calibrated)."""
    theta, a, d, alpha = _dh(arm)
    return _sub(StateType.KINEMATICS, "6I24dI", *([0] * 6), *theta, *a, *d, *alpha, 0)


def configuration(arm: URArm) -> bytes:
    lim, spec = arm.tool.arm.limits, arm.tool.arm.spec
    theta, a, d, alpha = _dh(arm)
    positions = [float(x) for pair in zip(lim.q_min, lim.q_max, strict=True) for x in pair]
    motion = [float(x) for pair in zip(lim.v_max, lim.a_max, strict=True) for x in pair]
    return _sub(
        StateType.CONFIGURATION,
        "12d12d5d24d4i",
        *positions,
        *motion,
        V_JOINT,
        A_JOINT,
        V_TOOL,
        A_TOOL,
        EQ_RADIUS,
        *a,
        *d,
        *alpha,
        *theta,
        MASTERBOARD_VERSION,
        CONTROLLER_BOX,
        ROBOT_TYPE.get(spec.name, 2),
        E_SERIES,
    )


def force_mode() -> bytes:
    return _sub(StateType.FORCE_MODE, "7d", *([0.0] * 7))  # (no force mode: no wrench, dexterity 0)


def additional() -> bytes:
    return _sub(StateType.ADDITIONAL, "B??B", 0, False, False, 0)  # (no freedrive button pressed)


def robot_state(arm: URArm, t_us: int) -> bytes:
    """The whole package for the arm's state now (its last update())."""
    parts = (
        robot_mode(arm, t_us),
        joints(arm),
        tool(arm),
        masterboard(arm),
        cartesian(arm),
        kinematics(arm),
        configuration(arm),
        force_mode(),
        additional(),
    )
    body = b"".join(parts)
    return _HEADER.pack(_HEADER.size + len(body), ROBOT_STATE) + body


def read_robot_state(body: bytes) -> dict[int, bytes]:
    """A robot state package's sub-packages (body: after the package's header): type -> its fields.
    ValueError if a length runs past the package.  (For clients and tests.)"""
    out: dict[int, bytes] = {}
    at = 0
    while at < len(body):
        if len(body) - at < _HEADER.size:
            raise ValueError(f"a sub-package header cut at byte {at}")
        size, kind = _HEADER.unpack_from(body, at)
        if size < _HEADER.size or at + size > len(body):
            raise ValueError(f"sub-package {kind} of {size} bytes at byte {at} runs past the package")
        out[kind] = body[at + _HEADER.size : at + size]
        at += size
    return out


def joint_positions(fields: bytes) -> np.ndarray:
    """q_actual of each joint in a joint data sub-package's fields."""
    n = len(fields) // 41
    return np.array([struct.unpack_from(">d", fields, 41 * j)[0] for j in range(n)])
