"""The robot state package of 30001/30002, sans IO: byte by byte, as UR's client interface document
(PolyScope 5.x) lays its sub-packages out and UR's client library reads them."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from cell.robot.arm import arm_model
from cell.ur import robotstate
from cell.ur.arm import RobotMode, RuntimeState, SafetyMode, URArm
from cell.ur.primary import split
from cell.ur.robotstate import StateType, read_robot_state, robot_state

Q = np.array([0.1, -1.5, 1.4, -1.6, -1.5, 0.2])
QD = np.array([0.05, 0.0, -0.02, 0.0, 0.0, 0.01])
# each sub-package's size in 5.x, its header included (the masterboard's without Euromap67)
SIZES = {0: 47, 1: 251, 2: 37, 3: 75, 4: 101, 5: 225, 6: 445, 7: 61, 8: 9}


def arm() -> URArm:
    ur = URArm("r1", arm_model("ur5e"))
    ur.update(Q, QD, np.zeros(6), 12.5)
    return ur


def test_one_package_of_type_16_whose_sub_packages_chain_to_its_end() -> None:
    data = bytearray(robot_state(arm(), 12_500_000))
    ((kind, body),) = split(data)  # (one whole package, nothing left over)
    assert kind == 16 and not data
    subs = read_robot_state(body)
    assert {k: len(v) + 5 for k, v in subs.items()} == SIZES
    assert len(body) + 5 < 2000  # (python-urx takes no bigger package)
    with pytest.raises(ValueError, match="runs past"):
        read_robot_state(body[:-3])


def test_robot_mode_data_says_what_the_arm_is_doing() -> None:
    ur = arm()
    fields = read_robot_state(robot_state(ur, 7)[5:])[StateType.ROBOT_MODE]
    got = struct.unpack(">Q7?bBdddB", fields)
    # timestamp, connected, enabled, powered, e-stopped, protective stop, running, paused, robot mode,
    # control mode, speed fraction, speed scaling, its limit, reserved
    assert got == (7, True, True, True, False, False, True, False, 7, 0, 1.0, 1.0, 1.0, 0)
    ur.safety_mode, ur.runtime, ur.speed_fraction = SafetyMode.PROTECTIVE_STOP, RuntimeState.PAUSED, 0.5
    got = struct.unpack(">Q7?bBdddB", read_robot_state(robot_state(ur, 7)[5:])[StateType.ROBOT_MODE])
    assert got[5:8] == (True, False, True) and got[10:12] == (0.5, 0.0)  # stopped: no speed
    ur.robot_mode = RobotMode.POWER_OFF
    got = struct.unpack(">Q7?bBdddB", read_robot_state(robot_state(ur, 7)[5:])[StateType.ROBOT_MODE])
    assert got[3] is False and got[8] == 3


def test_joints_tool_pose_and_calibration_are_the_arms() -> None:
    ur = arm()
    ur.tool.set_tcp(np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.5]))
    ur.digital_out, ur.digital_in = 0b101, 0b10
    subs = read_robot_state(robot_state(ur, 0)[5:])
    joints = [struct.unpack_from(">dddffffB", subs[StateType.JOINT], 41 * j) for j in range(6)]
    assert [j[0] for j in joints] == Q.tolist() and [j[2] for j in joints] == QD.tolist()
    assert {j[7] for j in joints} == {253}  # JOINT_RUNNING_MODE
    assert robotstate.joint_positions(subs[StateType.JOINT]).tolist() == Q.tolist()
    cart = struct.unpack(">12d", subs[StateType.CARTESIAN])
    assert cart[:6] == tuple(ur.tool.fk(Q).tolist()) and cart[6:] == (0.0, 0.0, 0.1, 0.0, 0.0, 0.5)
    kin = struct.unpack(">6I24dI", subs[StateType.KINEMATICS])
    spec = arm_model("ur5e").spec
    assert kin[12:18] == tuple(spec.a) and kin[18:24] == tuple(spec.d) and kin[24:30] == tuple(spec.alpha)
    board = struct.unpack_from(">II", subs[StateType.MASTERBOARD])
    assert board == (0b10, 0b101)
    conf = struct.unpack(">12d12d5d24d4i", subs[StateType.CONFIGURATION])
    lim = arm_model("ur5e").limits
    assert conf[0:2] == (lim.q_min[0], lim.q_max[0]) and conf[12:14] == (lim.v_max[0], lim.a_max[0])
    assert conf[-2] == 2  # a UR5
