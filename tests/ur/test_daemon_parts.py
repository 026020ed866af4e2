"""The daemon's parts on their own, no sockets: the RTDE client against the controller's own session
byte for byte, the daemon's program as URScript and as the emulated arm runs it, and the table that
says from the controller's state whether the program drives the arm."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from cell.robot.arm import arm_model
from cell.ur.arm import CONTROLLER_VERSION, RobotMode, RuntimeState, SafetyMode, URArm
from cell.ur.client import Client, SetupRefused, Step
from cell.ur.daemon import Registers, script
from cell.ur.fields import INPUTS, OUTPUTS
from cell.ur.program import DaemonProgram, runner
from cell.ur.remote import DaemonState, judge
from cell.ur.rtde import Package, Session, encode
from cell.ur.urscript import Framer, ScriptError, parse

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
REGS = Registers(24)


def _arm() -> URArm:
    arm = URArm("r1", arm_model("ur5e"), program="")
    arm.update(Q0, np.zeros(6), np.zeros(6), 0.002)
    return arm


def _talk(client: Client, session: Session) -> list[tuple]:
    """Run the handshake to its end: each side's bytes to the other until nothing is left to say."""
    out = session.receive(client.hello())
    got: list[tuple] = []
    while out:
        got += client.feed(b"".join(out))
        sent, client.outbox = bytes(client.outbox), bytearray()
        out = session.receive(sent) if sent else []
    return got


def test_the_client_hand_shakes_step_by_step_and_reads_data_packages() -> None:
    arm = _arm()
    session = Session(OUTPUTS, INPUTS, arm, CONTROLLER_VERSION)
    client = Client(
        ["timestamp", "actual_q", "robot_mode", REGS.heartbeat], [REGS.window, *REGS.velocities], 500
    )
    assert client.hello() == struct.pack(">HBH", 5, ord("V"), 2)
    _talk(client, session)
    assert client.step == Step.STARTED and session.started
    assert client.controller == CONTROLLER_VERSION
    arm.int_out[25] = 41
    (pkg,) = session.due(0, arm)
    (values,) = client.feed(pkg)
    assert values == (0.002, tuple(Q0), int(RobotMode.RUNNING), 41)
    # an input package sets the window's number and the six velocities, as the session reads them
    data = client.write((7, 0.1, -0.2, 0.3, 0.0, 0.0, 0.5))
    assert data == encode(Package.DATA_PACKAGE, b"\x01" + struct.pack(">i6d", 7, 0.1, -0.2, 0.3, 0, 0, 0.5))
    session.receive(data)
    assert arm.int_in[24] == 7 and arm.double_in[24:30] == [0.1, -0.2, 0.3, 0.0, 0.0, 0.5]


def test_the_client_says_which_fields_the_controller_refused() -> None:
    arm = _arm()
    with pytest.raises(SetupRefused, match=r"output fields: no_such_field \(NOT_FOUND\)"):
        _talk(
            Client(["timestamp", "no_such_field"], [], 500), Session(OUTPUTS, INPUTS, arm, CONTROLLER_VERSION)
        )
    holder = Session(OUTPUTS, INPUTS, arm, CONTROLLER_VERSION)
    _talk(Client(["timestamp"], [REGS.window], 500), holder)  # another client holds the window register
    with pytest.raises(SetupRefused, match=r"input fields: input_int_register_24 \(IN_USE\)"):
        _talk(Client(["timestamp"], [REGS.window], 500), Session(OUTPUTS, INPUTS, arm, CONTROLLER_VERSION))


def test_a_data_package_the_client_cannot_read_is_counted_and_dropped() -> None:
    arm = _arm()
    session = Session(OUTPUTS, INPUTS, arm, CONTROLLER_VERSION)
    client = Client(["timestamp"], [], 500)
    _talk(client, session)
    (good,) = session.due(0, arm)
    short = encode(Package.DATA_PACKAGE, good[3:-1])
    other_recipe = encode(Package.DATA_PACKAGE, b"\x09" + good[4:])
    assert client.feed(short + other_recipe + good) == [(0.002,)]
    assert client.malformed == 2


V_MAX, A_MAX = [3.0, 3.0, 3.0, 3.0, 3.0, 3.0], [5.0, 5.0, 5.0, 10.0, 10.0, 10.0]


def test_the_daemon_program_is_urscript_the_arm_frames_and_reads_its_settings_from() -> None:
    text = script(REGS, 16, V_MAX, A_MAX)
    (program,) = Framer().feed(text.encode())
    s = parse(program)
    assert (s.kind, s.name) == ("cell_daemon", "cell_daemon")
    assert s.settings == {"registers": 24.0, "watchdog": 16.0, "v_max": tuple(V_MAX), "a_max": tuple(A_MAX)}
    for reg in range(24, 30):  # it reads the six velocity registers, and writes back two ints
        assert f"read_input_float_register({reg})" in text
    assert (
        "write_output_integer_register(24, window)" in text
        and "write_output_integer_register(25, beat)" in text
    )
    with pytest.raises(ScriptError, match="cell_registers = 45"):
        parse(text.replace("global cell_registers = 24", "global cell_registers = 45"))
    with pytest.raises(ScriptError, match="cell_a_max"):
        parse(text.replace("global cell_a_max = [5, 5, 5,", "global cell_a_max = [5, 5,"))
    with pytest.raises(ScriptError, match="cell_v_max"):
        parse(text.replace("global cell_v_max = [3,", "global cell_v_max = [0,"))
    with pytest.raises(ScriptError, match="is not a number"):
        parse(text.replace("global cell_watchdog = 16", "global cell_watchdog = 1e"))


def test_the_emulated_arm_runs_the_daemon_program_as_a_ur_would() -> None:
    arm = _arm()
    prog = runner(parse(script(REGS, 4, V_MAX, A_MAX)), arm)
    assert isinstance(prog, DaemonProgram)
    q, qd, dt = Q0.copy(), np.zeros(6), 0.002
    # each joint toward its command within its own limits: 5 or 10 rad/s^2 (0.01, 0.02 a cycle), 3 rad/s
    arm.int_in[24], arm.double_in[24:30] = 1, [0.015, 0, 0, 0.005, 0, -9.0]
    v = prog.step(q, qd, dt)
    assert v == pytest.approx([0.01, 0, 0, 0.005, 0, -0.02])
    assert (arm.int_out[24], arm.int_out[25]) == (1, 1)  # the window taken, the heartbeat
    for _ in range(3):
        v = prog.step(q, v, dt)
    assert v == pytest.approx([0.015, 0, 0, 0.005, 0, -0.08]) and arm.int_out[25] == 4
    # the window's number has not changed for 3 cycles; on the 4th (`watchdog`) the program brings the
    # joints down at their accelerations
    v = prog.step(q, v, dt)
    assert v == pytest.approx([0.005, 0, 0, 0, 0, -0.06])
    for _ in range(3):
        v = prog.step(q, v, dt)
    assert not v.any()
    arm.int_in[24] = 2  # a new window: it takes the velocities again
    assert prog.step(q, v, dt) == pytest.approx([0.01, 0, 0, 0.005, 0, -0.02])
    assert arm.int_out[24] == 2


R, S, P = RobotMode.RUNNING, SafetyMode.NORMAL, RuntimeState.PLAYING


@pytest.mark.parametrize(
    ("robot", "safety", "runtime", "beating", "starting", "state"),
    [
        (R, S, P, True, False, DaemonState.RUNNING),
        (R, SafetyMode.REDUCED, P, True, False, DaemonState.RUNNING),
        (R, S, P, True, True, DaemonState.RUNNING),  # (its heartbeat is the proof: sent or not)
        (R, S, P, False, True, DaemonState.STARTING),
        (R, S, P, False, False, DaemonState.HELD),  # another program plays
        (R, S, RuntimeState.PAUSED, False, False, DaemonState.HELD),
        (R, S, RuntimeState.STOPPED, False, False, DaemonState.STOPPED),
        (R, S, RuntimeState.STOPPED, False, True, DaemonState.STARTING),
        (RobotMode.POWER_OFF, S, RuntimeState.STOPPED, False, False, DaemonState.BLOCKED),
        (RobotMode.IDLE, S, RuntimeState.STOPPED, False, False, DaemonState.BLOCKED),  # braked
        (R, SafetyMode.PROTECTIVE_STOP, P, True, False, DaemonState.BLOCKED),
        (R, SafetyMode.ROBOT_EMERGENCY_STOP, RuntimeState.STOPPED, False, False, DaemonState.BLOCKED),
    ],
)
def test_the_controllers_state_says_whether_the_daemon_drives_the_arm(
    robot: int, safety: int, runtime: int, beating: bool, starting: bool, state: DaemonState
) -> None:
    assert judge(robot, safety, runtime, beating, starting) == state
