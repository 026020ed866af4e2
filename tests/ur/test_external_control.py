"""UR's external_control program served natively (cell.ur.external), sans IO: its three sockets'
messages byte by byte, and its main loop, trajectory thread and script commands stepped on a
kinematic arm (q advanced by the commanded velocity each tick)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from cell.robot.arm import arm_model
from cell.ur.arm import URArm
from cell.ur.external import (
    COMMAND,
    POINT,
    RESULT,
    REVERSE,
    Command,
    ExternalControl,
    Mode,
    MotionType,
    Result,
    TrajectoryAction,
    client_program,
    read_settings,
)
from cell.ur.program import SocketState, runner
from cell.ur.urscript import Framer, ScriptError, parse

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
M = 1_000_000
DT = 0.002
PORTS = {"trajectory_socket": 50003, "script_command_socket": 50004, "reverse_socket": 50001}


def program(edit: Callable[[str], str] = lambda text: text) -> tuple[ExternalControl, URArm]:
    """The program as a client sends it (edited first, as UR's client library's tests edit it),
    taken by an arm, its sockets connected."""
    (stop, text) = Framer().feed(edit(client_program("127.0.0.1", PORTS, lookahead=0.05)).encode())
    assert stop == "stop program\n"  # (a line of its own: the primary interface's own command)
    st = URArm("r1", arm_model("ur5e"))
    r = runner(parse(text), st)
    assert isinstance(r, ExternalControl)
    r.connected = True
    return r, st


def reverse(mode: Mode, values=(0, 0, 0, 0, 0, 0), timeout_ms: int = 100) -> bytes:
    return REVERSE.pack(timeout_ms, *values, mode)


def joints(q) -> list[int]:
    return [round(v * M) for v in q]


def spline(q, qd, qdd=None, t: float = 1.0) -> bytes:
    kind = 1 if qdd is None else 2
    acc = joints(qdd if qdd is not None else [0] * 6)
    return POINT.pack(*joints(q), *joints(qd), *acc, round(t * M), kind, MotionType.SPLINE)


class Arm:
    """A kinematic arm under the program: each tick q moves by the velocity it commands."""

    def __init__(self, r: ExternalControl, q=Q0) -> None:
        self.r, self.q, self.qd = r, np.array(q, float), np.zeros(6)

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            if self.r.ended is not None:
                return
            self.qd = self.r.step(self.q, self.qd, DT)
            self.q = self.q + self.qd * DT


def results(r: ExternalControl, name: str = "trajectory_socket") -> list[int]:
    buf = bytes(r.outbox[name])
    r.outbox[name].clear()
    return [RESULT.unpack_from(buf, i)[0] for i in range(0, len(buf), 4)]


def test_the_wire_formats_are_big_endian_int32s_of_urcls_lengths() -> None:
    assert (REVERSE.size, POINT.size, COMMAND.size, RESULT.size) == (32, 84, 112, 4)
    assert reverse(Mode.SERVOJ, (1, 2, 3, 4, 5, -6), 20) == bytes.fromhex(
        "000000140000000100000002000000030000000400000005fffffffa00000001"
    )


def test_what_the_client_filled_in_is_read_from_the_script() -> None:
    r, _ = program()
    s = read_settings(r.script)
    assert s.host == "127.0.0.1" and s.ports == {
        "trajectory_socket": 50003, "script_command_socket": 50004, "reverse_socket": 50001
    }  # fmt: skip
    assert (s.mult_joint, s.mult_time, s.lookahead, s.gain) == (1e6, 1e6, 0.05, 2000.0)
    text = client_program("127.0.0.1", PORTS).split("\n", 1)[1].replace('"script_command_socket"', '"x"')
    with pytest.raises(ScriptError, match="no connect_socket_with_retry for script_command_socket"):
        parse(text)


def test_until_connected_the_program_waits_and_its_first_read_blocks() -> None:
    r, _ = program()
    r.connected = False
    arm = Arm(r)
    arm.run(1.0)
    assert r.ended is None and not arm.qd.any()
    r.connected = True
    arm.run(2.0)  # (read timeout 0 until a message says otherwise: no keepalive yet)
    assert r.ended is None


def test_servoj_follows_the_stream_and_a_late_message_ends_the_program() -> None:
    r, _ = program()
    arm = Arm(r)
    goal = Q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.05, 0.3])
    for k in range(1, 601):  # 1 s ramp to the goal, one target a tick, then the goal held
        r.feed("reverse_socket", reverse(Mode.SERVOJ, joints(Q0 + (goal - Q0) * min(k, 500) / 500)))
        arm.run(DT)
    # under the 100 ms read timeout a tick without a target extrapolates the last one (standing)
    arm.run(0.08)
    assert r.ended is None and np.abs(arm.q - goal).max() < 1e-4, arm.q - goal
    arm.run(0.1)
    assert r.ended == "the reverse interface's read timed out"
    assert any("Socket timed out waiting for command on reverse_socket" in m.text for m in r.messages)


def test_ticks_its_process_was_late_for_are_no_silence_of_the_clients() -> None:
    """A program stepped through ticks its process is catching up on (RobotGroup.live False) has not
    read what its client sent meanwhile: those ticks do not count toward the read timeout."""
    r, _ = program()
    arm = Arm(r)
    r.feed("reverse_socket", reverse(Mode.SERVOJ, joints(Q0)))  # (a 100 ms read timeout)
    arm.run(DT)
    r.live = False
    arm.run(0.3)  # three timeouts' worth of ticks, caught up on
    assert r.ended is None
    r.live = True
    arm.run(0.08)
    assert r.ended is None
    arm.run(0.04)  # its own ticks do count
    assert r.ended == "the reverse interface's read timed out"


def test_a_servoj_target_beyond_20_rad_s_is_ignored_with_the_scripts_words() -> None:
    r, _ = program()
    arm = Arm(r)
    r.feed("reverse_socket", reverse(Mode.SERVOJ, joints(Q0 + np.array([0.1, 0, 0, 0, 0, 0]))))
    arm.run(DT)
    assert any("exceeding the joint velocity limits" in m.text for m in r.messages)
    assert r.servo is not None and np.allclose(r.servo.target, Q0, atol=1e-9)


def test_speedj_and_mode_stopped() -> None:
    r, _ = program()
    arm = Arm(r)
    for _ in range(250):
        r.feed("reverse_socket", reverse(Mode.SPEEDJ, joints([0.2, 0, 0, 0, 0, -0.1])))
        arm.run(DT)
    assert np.allclose(arm.qd, [0.2, 0, 0, 0, 0, -0.1])
    r.feed("reverse_socket", reverse(Mode.STOPPED))
    arm.run(DT)
    assert r.ended == ""


def appended(text: str) -> str:
    """The edit UR's client library's ExternalControlProgramTest makes: code after the loop."""
    assert text.endswith("\nend\n")
    return (
        text[:-4]
        + '\tsocket_open("127.0.0.1", 60005, "test_socket")\n\tsleep(0.6)\n\ttextmsg("done.")\nend\n'
    )


def test_code_after_the_control_loop_runs_once_control_is_stopped_and_not_after_a_timeout() -> None:
    """stop_control_does_not_halt_program and program_halts_on_timeout: the appended socket_open
    is reached only when the client stops control; a read timeout halts the program before it."""
    r, _ = program(appended)
    assert [c.name for c in r.script.tail] == ["socket_open", "sleep", "textmsg"]
    arm = Arm(r)
    for _ in range(100):
        r.feed("reverse_socket", reverse(Mode.SPEEDJ, joints([0.2, 0, 0, 0, 0, 0])))
        arm.run(DT)
    r.feed("reverse_socket", reverse(Mode.STOPPED))
    arm.run(0.2)  # stopj(4.0) first, then socket_open, which waits for the server to connect it
    s = r.sockets["test_socket"]
    assert r.ended is None and (s.host, s.port) == ("127.0.0.1", 60005) and not arm.qd.any()
    s.state = SocketState.OPEN
    arm.run(0.59)
    assert r.ended is None
    arm.run(0.02)
    assert r.ended == "" and r.messages[-1].text == "done."
    r, _ = program(appended)
    arm = Arm(r)
    r.feed("reverse_socket", reverse(Mode.IDLE, timeout_ms=20))
    arm.run(0.2)
    assert r.ended == "the reverse interface's read timed out" and not r.sockets


@pytest.mark.parametrize("quintic", [False, True])
def test_a_spline_trajectory_passes_its_points_and_answers_success(quintic: bool) -> None:
    r, _ = program()
    arm = Arm(r)
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 3, 0, 0, 0, 0), 200))
    d = np.array([0.3, -0.2, 0.2, 0.1, -0.1, 0.4])
    pts = [(Q0 + d * 0.5, d * 0.6), (Q0 + d, d * 0.2), (Q0 + d * 0.9, np.zeros(6))]
    for q, qd in pts:
        r.feed("trajectory_socket", spline(q, qd, np.zeros(6) if quintic else None, t=1.0))
    seen = []
    for _ in range(3):  # at each point's time, where the arm is
        for _ in range(500):
            r.feed("reverse_socket", reverse(Mode.FORWARD, (0, 0, 0, 0, 0, 0), 200))  # (the keepalive)
            arm.run(DT)
        seen.append(arm.q.copy())
    arm.run(0.1)
    for q, (goal, _) in zip(seen, pts, strict=True):
        assert np.abs(q - goal).max() < 2e-3, q - goal
    assert results(r) == [Result.SUCCESS]


def test_cancel_answers_canceled_and_a_missing_point_fails_the_trajectory() -> None:
    r, _ = program()
    arm = Arm(r)
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 2, 0, 0, 0, 0), 1000))
    r.feed("trajectory_socket", spline(Q0 + 0.2, np.zeros(6), t=2.0))
    arm.run(0.5)
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.CANCEL, 0, 0, 0, 0, 0), 1000))
    arm.run(0.5)
    assert results(r) == [Result.CANCELED] and np.abs(arm.qd).max() < 1e-3
    # two points announced, one sent: once the first is done the second is waited for one step
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 2, 0, 0, 0, 0), 1000))
    r.feed("trajectory_socket", spline(arm.q + 0.1, np.zeros(6), t=0.5))
    arm.run(0.7)
    assert results(r) == [Result.FAILURE]
    assert any(m.text == "Receiving trajectory point failed!" for m in r.messages)


def test_movej_points_with_a_time_take_that_time() -> None:
    r, _ = program()
    arm = Arm(r)
    goal = Q0 + np.array([0.4, 0, 0, 0, 0, 0])
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 1, 0, 0, 0, 0), 0))
    r.feed("trajectory_socket", POINT.pack(*joints(goal), *[0] * 12, 2 * M, 0, MotionType.MOVEJ))
    arm.run(1.0)
    assert 0.1 < abs(arm.q[0] - Q0[0]) < 0.3  # (half way in time, about half way)
    arm.run(1.5)
    assert np.abs(arm.q - goal).max() < 1e-4 and results(r) == [Result.SUCCESS]


def test_script_commands_set_the_tcp_and_payload_and_force_mode_is_refused() -> None:
    r, st = program()
    arm = Arm(r)
    tcp = [0, 0, 0.1, 0, 0, 0]
    r.feed("script_command_socket", COMMAND.pack(Command.SET_TCP_OFFSET, *joints(tcp), *[0] * 21))
    r.feed("script_command_socket", COMMAND.pack(Command.SET_PAYLOAD, 2 * M, 0, 0, 50_000, *[0] * 23))
    r.feed("script_command_socket", COMMAND.pack(Command.END_TOOL_CONTACT, *[0] * 27))
    arm.run(DT)
    assert st.values("tcp_offset") == tuple(tcp) and st.payload == 2.0 and st.cog == (0.0, 0.0, 0.05)
    assert results(r, "script_command_socket") == [1]  # (tool contact: canceled, never in contact)
    r.feed("script_command_socket", COMMAND.pack(Command.START_FORCE_MODE, *[0] * 27))
    arm.run(DT)
    assert r.ended is not None and "force_mode()" in r.ended
    assert r.messages[-1].line == 0  # (a runtime exception: the client sees it)


def test_a_closed_reverse_socket_ends_the_program_and_an_unknown_mode_is_ignored() -> None:
    r, _ = program()
    arm = Arm(r)
    r.feed("reverse_socket", REVERSE.pack(100, 0, 0, 0, 0, 0, 0, 42))
    arm.run(DT)
    assert r.ended is None and "unknown control mode 42" in r.messages[-1].text
    r.lost("reverse_socket")
    arm.run(DT)
    assert r.ended == ""


def test_the_last_spline_point_slows_to_a_stop_on_its_path_as_the_script_does() -> None:
    """A last point with an end velocity: near the end the segment's time is scaled down, so no joint
    is faster than braking at 15 rad/s^2 allows, the target stands at the end, and the spline time
    the script writes to its probe register (UR's client library's spline tests) reaches the end."""
    probe = "\twrite_output_float_register(1, splineTimerTraveled)\n"
    r, st = program(
        lambda text: text.replace("\t# NODE_CONTROL_LOOP_ENDS", probe + "\t# NODE_CONTROL_LOOP_ENDS")
    )
    assert r.settings.spline_register == 1
    arm = Arm(r)
    end_qd = 0.273 * np.array([0.5, 0.4, 0.3, 0.2, 0.1, 1.0])
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 1, 0, 0, 0, 0), 0))
    r.feed("trajectory_socket", spline(Q0, end_qd, t=2.0))
    worst = -1.0
    while not results(r):
        before = st.double_out[1]
        arm.run(DT)
        ref = r.reference()
        assert ref is not None
        worst = max(worst, float(np.abs(ref[1]).max()) - 15 * (2.0 - before))
    assert worst < 1e-3 and st.double_out[1] == pytest.approx(2.0, abs=1e-9)
    ref = r.reference()
    assert ref is not None and not ref[1].any()


def test_movec_takes_the_tool_through_the_via_point_on_a_circle() -> None:
    r, _ = program()
    arm = Arm(r)
    p0 = r.tool.fk(Q0)
    rot = p0[3:]
    # a quarter circle of radius 5 cm in the base's xy plane about (x0 - 5 cm, y0)
    c = p0[:3] - np.array([0.05, 0, 0])
    via = np.concatenate([c + 0.05 * np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0]), rot])
    goal = np.concatenate([c + 0.05 * np.array([0, 1, 0]), rot])
    raw = POINT.pack(*joints(goal), *joints(via), *joints([0.1, 0.5, 1, 0, 0, 0]), 0, 0, MotionType.MOVEC)
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 1, 0, 0, 0, 0), 0))
    r.feed("trajectory_socket", raw)
    radii, to_via = [], []
    while not results(r):
        arm.run(DT)
        tool = r.tool.fk(arm.q)[:3]
        radii.append(float(np.linalg.norm(tool - c)))
        to_via.append(float(np.linalg.norm(tool - via[:3])))
    assert np.abs(np.array(radii) - 0.05).max() < 2e-4  # (on the circle all the way)
    assert min(to_via) < 1e-3 and np.linalg.norm(r.tool.fk(arm.q)[:3] - goal[:3]) < 1e-5


def test_a_movej_beyond_a_joints_range_fails_and_a_script_without_the_cancel_answer_gives_none() -> None:
    r, _ = program()
    arm = Arm(r)
    r.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 1, 0, 0, 0, 0), 0))
    r.feed("trajectory_socket", POINT.pack(*joints([-123, 0, 0, 0, 0, 0]), *[0] * 12, 0, 0, MotionType.MOVEJ))
    arm.run(0.1)
    assert results(r) == [Result.FAILURE] and "outside its range" in r.messages[-2].text
    # UR's client library's test strips the script's canceled answer: then none is sent
    answer = 'socket_send_int(TRAJECTORY_RESULT_CANCELED, "trajectory_socket")'
    stripped, _ = program(lambda text: text.replace(answer, "sync()"))
    assert not stripped.settings.sends_canceled
    arm = Arm(stripped)
    stripped.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.RECEIVE, 1, 0, 0, 0, 0), 0))
    stripped.feed("trajectory_socket", spline(Q0 + 0.2, np.zeros(6), t=2.0))
    arm.run(0.2)
    stripped.feed("reverse_socket", reverse(Mode.FORWARD, (TrajectoryAction.CANCEL, 0, 0, 0, 0, 0), 0))
    arm.run(0.2)
    assert results(stripped) == [] and not stripped.traj_running
