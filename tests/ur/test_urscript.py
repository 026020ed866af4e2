"""URScript on the emulated arms, sans IO: framing, what is run and what is refused, the primary
interface's messages byte by byte, and ur_rtde's control-script register protocol stepped tick by tick."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from cell.robot.arm import arm_model
from cell.ur import primary
from cell.ur.arm import SafetyMode, URArm
from cell.ur.motion import AT_GOAL_RAD, MoveJ, MoveL, Speed, Trapezoid
from cell.ur.program import (
    CALLS_PER_TICK,
    CLIENT_GONE_S,
    DONE,
    READY,
    Cmd,
    LineRunner,
    RtdeControl,
    SocketState,
)
from cell.ur.urscript import END_LOOP, MAX_SCRIPT, Framer, Pose, Script, ScriptError, parse

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
DT = 0.002


def test_the_framer_cuts_programs_at_their_top_level_end_and_takes_one_liners() -> None:
    f = Framer()
    got = f.feed(b"def a():\n  if x:\n    movej([0,0,0,0,0,0])\n  end\n")
    assert got == []  # (the inner `end` is indented: the program goes on)
    got = f.feed(b'end\n\n# a comment\ntextmsg("hi")\r\ndef b():\n')
    assert got == ["def a():\n  if x:\n    movej([0,0,0,0,0,0])\n  end\nend\n", 'textmsg("hi")\n']
    assert f.feed(b"  sleep(1)\nend\n") == ["def b():\n  sleep(1)\nend\n"]
    assert f.feed(b"  sleep(2)\n") == ["sleep(2)\n"]  # (indented, outside a definition: one line)


def test_a_program_too_long_is_refused_and_the_next_one_is_taken() -> None:
    f = Framer()
    got = f.feed(b"def big():\n" + b"  sleep(1)\n" * (MAX_SCRIPT // 11 + 2) + b"end\ndef ok():\nend\n")
    assert isinstance(got[0], ScriptError) and "longer than" in got[0].reason
    assert got[1:] == ["def ok():\nend\n"] and f.refused == 1
    f = Framer()
    got = f.feed(b"x" * (MAX_SCRIPT + 1))  # one endless line: refused, and skipped to its end
    assert isinstance(got[0], ScriptError)
    assert f.feed(b"xx\ntextmsg(1)\n") == ["textmsg(1)\n"]
    got = f.feed(b"def a():\n" + b"y" * (MAX_SCRIPT + 1))  # in a program: skipped to the program's end
    assert isinstance(got[0], ScriptError)
    assert f.feed(b"y\n  sleep(1)\nend\ntextmsg(2)\n") == ["textmsg(2)\n"]


def test_ur_rtde_scripts_are_recognised_with_their_register_offsets() -> None:
    s = parse("def rtde_control():\n    global reg_offset_float = 24\n    global reg_offset_int = 24\nend\n")
    assert (s.kind, s.reg_offset_int, s.reg_offset_float) == ("rtde_control", 24, 24)


def test_a_straight_line_program_is_read_with_defaults_poses_and_arithmetic() -> None:
    s = parse(
        "def go():\n"
        "  movej([0, -1.57, 1.57, -pi/2, -1.57, 0], a=1.2)  # a comment\n"
        "  movel(p[0.1, 0.2, 0.3, 0, 3.14, 0], v=0.1)\n"
        '  textmsg("at #", 1)\n'
        "  set_standard_digital_out(2, True)\n"
        "end\n"
    )
    assert s.kind == "lines" and s.name == "go"
    movej, movel, text, out = s.calls
    assert (
        movej.args["q"][3] == pytest.approx(-np.pi / 2) and movej.args["a"] == 1.2 and movej.args["v"] == 1.05
    )
    assert movel.args["pose"] == Pose((0.1, 0.2, 0.3, 0.0, 3.14, 0.0)) and movel.line == 3
    assert text.args == {"s1": "at #", "s2": 1}
    assert out.args == {"n": 2, "b": True}


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("def x():\n  movej([0,0,0,0,0,0])\n  while True:\n", 3, "with no `end`"),
        ("def x():\n  while True:\n  end\n", 2, "empty `while True:`"),
        ("def x():\n  sync()\n  end\n", 3, "no `while True:` to close"),
        ("def x():\n  while n < 3:\n    sync()\n  end\n", 2, "`while`: this arm has no URScript interpreter"),
        ("def x():\n  if True:\n", 2, "`if`: this arm has no URScript interpreter"),
        ("def x():\n  n = 1\n", 2, "an assignment"),
        ("def x():\n  sleep(1)\n  force_mode(p[0,0,0,0,0,0], [0,0,1,0,0,0])\n", 3, "force_mode() is not run"),
        ("def x():\n  1 + 2\n", 2, "not a call"),
        ("def x():\n  movej(q)\n", 2, "not a literal"),
        ("def x():\n  movej([0,0,0,0,0,0], speed=1)\n", 2, "no parameter 'speed'"),
        ("def x():\n  stopj()\n", 2, "needs a"),
        ("movel(p[0, 0, 0])\n", 1, "a pose is"),
        ("sleep(" + "1+" * 3000 + "1)\n", 1, "nested too deep"),
        ("sleep(" + "(" * 300 + "1" + ")" * 300 + ")\n", 1, "cannot read"),
        ("sleep(" + "1" * 20000 + ")\n", 1, "a line of 20007 characters"),
    ],
)
def test_what_the_arm_does_not_run_is_refused_with_its_line(text: str, line: int, words: str) -> None:
    with pytest.raises(ScriptError) as err:
        parse(text + ("end\n" if text.startswith("def") else ""))
    assert err.value.line == line and words in err.value.reason


def test_a_function_no_ur_has_is_refused_in_the_compilers_words_at_its_column() -> None:
    """As UR's client library's test_program_execution_reports_exception reads a UR's answer."""
    with pytest.raises(ScriptError) as err:
        parse("def illegal_fun():\n  calldoesntexist()\nend\n")
    e = err.value
    assert (e.line, e.column, e.said) == (2, 3, "compile_error_name_not_found:calldoesntexist:")
    with pytest.raises(ScriptError) as err:  # (a UR has this one: not run here, and said so)
        parse("def f():\n\tget_actual_tcp_speed()\nend\n")
    assert (err.value.column, err.value.said) == (2, f"program refused: {err.value.reason}")
    assert "get_actual_tcp_speed() is not run by this arm" in err.value.reason


def test_a_while_true_loop_becomes_a_jump_back_to_its_first_call() -> None:
    s = parse(
        'def f():\n  textmsg("a")\n  while True:\n    sleep(1.0)\n    while (True):\n      sync()\n'
        "    end\n  end\nend\n"
    )
    assert [(c.name, c.args.get("to"), c.line) for c in s.calls] == [
        ("textmsg", None, 2), ("sleep", None, 4), ("sync", None, 6), (END_LOOP, 2, 7), (END_LOOP, 1, 8),
    ]  # fmt: skip


def test_primary_messages_byte_by_byte() -> None:
    v = primary.version(7, 5, 11, 0, 108249)
    assert v[:5] == struct.pack(">iB", len(v), 20)
    assert v[5:15] == struct.pack(">QbB", 7, -2, 3)
    assert v[15:] == b"\x09URControl" + struct.pack(">BBii", 5, 11, 0, 108249)
    e = primary.runtime_exception(9, 3, 2, "no")
    assert e == struct.pack(">iBQbBii", 25, 20, 9, -2, 10, 3, 2) + b"no"
    (kind, body), (kind2, body2) = primary.split(bytearray(e + primary.text(1, "hi")))
    assert kind == kind2 == 20
    assert primary.read_robot_message(body) == (
        primary.RobotMessage.RUNTIME_EXCEPTION,
        struct.pack(">ii", 3, 2) + b"no",
    )
    assert primary.read_robot_message(body2) == (primary.RobotMessage.TEXT, b"hi")
    # an error code, as UR's client library parses it: code, argument, report level, data type, data
    c = primary.error_code(5, 209, 0, primary.ReportLevel.VIOLATION, "stop")
    assert c == struct.pack(">iBQbBiiiII", 39, 20, 5, -2, 6, 209, 0, 3, 0, 0) + b"stop"
    # a key message: code, argument, the title's length, the title, the text (a program's name)
    m = primary.safety_mode(5, 3)  # (PROTECTIVE_STOP)
    assert m == struct.pack(">iBQbBiiBII", 32, 20, 5, -2, 5, 0, 0, 3, 0, 0)
    k = primary.key_message(5, "PROGRAM_XXX_STARTED", "test_fun")
    assert k == struct.pack(">iBQbBiiB", 51, 20, 5, -2, 7, 0, 0, 19) + b"PROGRAM_XXX_STARTEDtest_fun"


@pytest.mark.parametrize(
    ("text", "secondary"),
    [('sec s():\n  textmsg("x")\nend\n', True), ('def s():\n  textmsg("x")\nend\n', False)],
)
def test_a_sec_program_is_a_secondary_one(text: str, secondary: bool) -> None:
    assert parse(text).secondary is secondary


# --- the motions and the runners, on a simulated arm that follows its commands exactly --------------


class Arm:
    """Joints that take the commanded velocity within the model's acceleration, as the drives do."""

    def __init__(self) -> None:
        self.model = arm_model("ur5e")
        self.q, self.qd = Q0.copy(), np.zeros(6)

    def run(self, step, ticks: int) -> list[np.ndarray]:
        seen = []
        for _ in range(ticks):
            v = step(self.q, self.qd, DT)
            a = self.model.limits.a_max * DT
            new = self.qd + np.clip(
                np.clip(v, -self.model.limits.v_max, self.model.limits.v_max) - self.qd, -a, a
            )
            self.q = self.q + 0.5 * (self.qd + new) * DT
            self.qd = new
            seen.append(self.qd.copy())
        return seen


def test_trapezoids_reach_their_length_at_rest() -> None:
    for length, v, a in ((1.0, 1.0, 1.4), (0.05, 1.0, 1.4), (0.0, 1.0, 1.0)):
        p = Trapezoid.make(length, v, a)
        assert p.at(p.duration) == (pytest.approx(length), 0.0)
        assert max(p.at(t)[1] for t in np.linspace(0, p.duration, 200)) <= v + 1e-12


def test_movej_moves_every_joint_on_one_profile_and_ends_on_the_goal() -> None:
    arm = Arm()
    goal = Q0 + np.array([0.4, -0.2, 0.1, 0.0, 0.3, -1.0])
    m = MoveJ(arm.q, goal, v=1.0, a=1.4, arm=arm.model)
    arm.run(m.step, round(m.profile.duration / DT) + 200)
    assert m.done and not m.error
    assert np.abs(arm.q - goal).max() <= AT_GOAL_RAD
    # the leading joint (wrist 3, 1 rad) cruises at v; the others in proportion (one profile)
    assert m.profile.v == pytest.approx(1.0)


def test_movel_keeps_the_tool_on_its_line() -> None:
    arm = Arm()
    tool = URArm("r1", arm.model).tool
    p0 = tool.fk(arm.q)
    goal = p0 + np.array([0.1, 0.05, -0.1, 0, 0, 0])
    m = MoveL(arm.q, goal, v=0.25, a=1.2, tool=tool)
    off = []
    for _ in range(round(m.profile.duration / DT) + 300):
        arm.run(m.step, 1)
        x = tool.fk(arm.q)[:3]
        d = goal[:3] - p0[:3]
        off.append(np.linalg.norm(np.cross(x - p0[:3], d)) / np.linalg.norm(d))
    assert m.done and not m.error
    assert np.abs(tool.fk(arm.q)[:3] - goal[:3]).max() < 1e-4
    assert max(off) < 5e-4  # within half a millimetre of the straight line all the way


def test_a_stop_decelerates_at_the_rate_asked_and_ends_at_rest() -> None:
    arm = Arm()
    s = Speed(arm.qd, np.array([0.5, 0, 0, 0, 0, 0]), a=2.0)
    arm.run(s.step, 400)
    assert arm.qd[0] == pytest.approx(0.5)
    stop = Speed(arm.qd, np.zeros(6), a=1.0, stop=True)
    seen = arm.run(stop.step, 400)
    assert stop.done
    dv = -np.diff([v[0] for v in seen]) / DT
    assert dv.max() <= 1.0 + 1e-9  # never harder than asked
    assert sum(1 for v in seen if v[0] > 0) * DT == pytest.approx(0.5, abs=0.01)  # 0.5 rad/s at 1 rad/s^2


def control(arm: URArm) -> RtdeControl:
    return RtdeControl(Script("rtde_control", "rtde_control"), arm)


def test_the_control_script_answers_ready_then_done_and_takes_the_next_command_after_a_clear() -> None:
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    ctl = control(ur)
    assert ur.int_out[0] == READY
    ur.claim("client", ["input_int_register_0"])
    goal = Q0 + np.array([0.2, 0, 0, 0, 0, 0])
    ur.int_in[0], ur.int_in[1] = Cmd.MOVEJ, 0
    ur.double_in[:8] = [*goal, 1.0, 1.4]
    sim.run(ctl.step, 1)
    assert ur.int_out[0] == READY  # (a synchronous move: answered at its end)
    sim.run(ctl.step, 600)
    assert ur.int_out[0] == DONE and np.abs(sim.q - goal).max() <= AT_GOAL_RAD
    ur.int_in[0] = Cmd.IS_STEADY  # not taken before the client clears the last command
    sim.run(ctl.step, 3)
    assert ur.int_out[0] == DONE and ur.int_out[1] == 0
    ur.int_in[0] = Cmd.NO_CMD
    sim.run(ctl.step, 1)
    assert ur.int_out[0] == READY
    ur.int_in[0] = Cmd.IS_STEADY
    sim.run(ctl.step, 1)
    assert ur.int_out[0] == DONE and ur.int_out[1] == 1
    ur.int_in[0] = Cmd.NO_CMD
    sim.run(ctl.step, 1)
    ur.int_in[0] = Cmd.GET_FORWARD_KINEMATICS_DEFAULT
    sim.run(ctl.step, 1)
    assert np.allclose(ur.double_out[:6], ur.tool.fk(sim.q), atol=1e-4)  # (the q it was read at)


def test_an_async_move_reports_progress_and_a_stopj_ends_it() -> None:
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    ctl = control(ur)
    ur.claim("client", ["input_int_register_0"])
    idle = ur.int_out[2]
    assert not idle & 0x8000  # no operation running
    ur.int_in[0], ur.int_in[1] = Cmd.MOVEJ, 1
    ur.double_in[:8] = [*(Q0 + 1.0), 1.0, 1.4]
    sim.run(ctl.step, 1)
    assert ur.int_out[0] == DONE and ur.int_out[2] & 0x8000  # answered at once, and running
    op = ur.int_out[2] >> 24
    ur.int_in[0] = Cmd.NO_CMD
    sim.run(ctl.step, 100)
    ur.int_in[0], ur.double_in[0] = Cmd.STOPJ, 2.0
    sim.run(ctl.step, 2)
    assert not ur.int_out[2] & 0x8000 and ur.int_out[2] >> 24 == op  # that operation has finished
    sim.run(ctl.step, 400)
    assert ur.int_out[0] == DONE and np.abs(sim.qd).max() < 1e-3


def test_what_the_control_script_cannot_do_ends_it_with_the_reason() -> None:
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    ctl = control(ur)
    ur.int_in[0], ur.int_out[0] = 6, 0  # force_mode
    sim.run(ctl.step, 1)
    assert ctl.ended == "ur_rtde command 6 is not emulated" and ctl.messages
    assert ur.int_out[0] != READY  # never acknowledged: the client's forceMode() fails
    ctl = control(ur)
    ur.int_in[0] = Cmd.NO_CMD
    sim.run(ctl.step, 1)
    ur.int_in[0] = Cmd.MOVEJ_IK
    ur.double_in[:8] = [5.0, 0, 0, 0, 0, 0, 1.0, 1.0]  # 5 m away
    sim.run(ctl.step, 1)
    assert "no joint positions reach" in ctl.ended and np.allclose(sim.q, Q0)
    ctl = control(ur)
    ur.int_in[0] = Cmd.PROTECTIVE_STOP
    sim.run(ctl.step, 1)
    assert ur.safety_mode == SafetyMode.PROTECTIVE_STOP and "protective stop" in ctl.ended


def test_a_servoj_target_that_is_not_a_number_ends_the_script_and_the_arm_stays_sound() -> None:
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    ctl = control(ur)
    ur.int_in[0] = Cmd.SERVOJ
    ur.double_in[:11] = [*(Q0 + 0.01), 0, 0, 0.002, 0.1, 300]
    sim.run(ctl.step, 5)
    assert ctl.ended is None and sim.qd.any()
    ur.double_in[2] = float("nan")  # (a client's bug, sent over RTDE)
    sim.run(ctl.step, 1)
    assert ctl.ended is not None and "servoj(): not a number" in ctl.ended
    assert any("not a number" in m.text for m in ctl.messages)
    assert np.isfinite(sim.q).all() and np.isfinite(sim.qd).all()


def test_the_control_script_stops_when_its_rtde_client_goes() -> None:
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    ctl = control(ur)
    ur.claim("client", ["input_int_register_0"])
    ur.int_in[0] = Cmd.SERVOJ
    ur.double_in[:11] = [*(Q0 + 0.01), 0, 0, 0.002, 0.1, 300]
    sim.run(ctl.step, 5)
    assert ctl.ended is None and sim.qd.any()
    now = [0.0]
    ctl.clock = lambda: now[0]
    ur.release("client")
    sim.run(ctl.step, 1)  # gone: the arm is stopped, the script waits a moment for a client
    assert ctl.ended is None
    now[0] += CLIENT_GONE_S / 2
    ur.claim("again", ["input_int_register_0"])  # (ur_rtde's reuploadScript() connects anew)
    sim.run(ctl.step, 1)
    ur.release("again")
    sim.run(ctl.step, 1)
    now[0] += CLIENT_GONE_S * 0.9  # (gone, in all, longer than CLIENT_GONE_S; this time, not)
    sim.run(ctl.step, 1)
    assert ctl.ended is None
    now[0] += CLIENT_GONE_S * 0.2
    sim.run(ctl.step, 1)
    assert ctl.ended == "the RTDE client driving the control script disconnected"


def test_a_line_program_runs_its_calls_in_order() -> None:
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    script = parse(
        "def go():\n  set_standard_digital_out(1, True)\n"
        "  movej([0.2, -1.5708, 1.5708, -1.5708, -1.5708, 0])\n"
        '  textmsg("there")\n  sleep(0.1)\nend\n'
    )
    r = LineRunner(script, ur)
    sim.run(r.step, 1)
    assert ur.digital_out == 2 and r.ended is None
    ticks = 1
    while r.ended is None:
        sim.run(r.step, 1)
        ticks += 1
        assert ticks < 2000
    assert r.ended == "" and abs(sim.q[0] - 0.2) <= AT_GOAL_RAD
    assert [m.text for m in r.messages] == ["there"]


def test_a_loop_runs_until_stopped_and_one_that_takes_no_time_ends_with_a_runtime_exception() -> None:
    """UR's client library's test_stop_command: textmsg, sleep(1.0), sync() for ever."""
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    r = LineRunner(
        parse('def f():\n  while True:\n    textmsg("still")\n    sleep(0.01)\n    sync()\n  end\nend\n'), ur
    )
    sim.run(r.step, 100)  # 0.2 s: 0.01 s and a tick a pass
    assert r.ended is None and 15 <= [m.text for m in r.messages].count("still") <= 17
    q = sim.q.copy()
    # a loop back to a move where the arm stands: each pass still takes a tick, as on a UR
    r = LineRunner(parse(f"def f():\n  while True:\n    movej({[float(x) for x in q]})\n  end\nend\n"), ur)
    sim.run(r.step, 50)
    assert r.ended is None
    r = LineRunner(parse('def f():\n  while True:\n    textmsg("x")\n  end\nend\n'), ur)
    sim.run(r.step, 1)
    assert r.ended is not None and "takes no time" in r.ended
    assert r.messages[-1].line == 3 and len(r.messages) <= CALLS_PER_TICK + 1


def test_socket_open_waits_to_be_connected_and_sends_then_closes() -> None:
    """The program's side (the server connects it): socket_open blocks until OPEN or FAILED."""
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    r = LineRunner(
        parse(
            'def f():\n  socket_open("127.0.0.1", 60005, "s")\n  socket_send_line("hi", "s")\n'
            '  socket_send_string("x", socket_name="s")\n  socket_close("s")\n'
            '  socket_open("127.0.0.1", 60006)\n  textmsg("after")\nend\n'
        ),
        ur,
    )
    sim.run(r.step, 3)
    s = r.sockets["s"]
    assert (s.host, s.port, s.timeout, s.state) == ("127.0.0.1", 60005, 2.0, SocketState.OPENING)
    assert r.ended is None and not r.messages
    s.state = SocketState.OPEN
    sim.run(r.step, 1)
    assert s.outbox == b"hi\nx" and s.state == SocketState.CLOSED and r.sockets["socket_0"].port == 60006
    r.sockets["socket_0"].state = SocketState.FAILED  # (socket_open returns False; the program goes on)
    sim.run(r.step, 1)
    assert r.ended == "" and [m.text for m in r.messages] == ["after"]


def test_protective_stop_stops_the_arm_and_ends_the_program() -> None:
    """What UR's client library's dashboard test sends on the primary interface."""
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    r = LineRunner(parse("protective_stop()\n"), ur)
    sim.run(r.step, 1)
    assert r.ended == "a protective stop (protective_stop())" and ur.safety_mode == SafetyMode.PROTECTIVE_STOP
    assert not ur.can_move


def test_the_tcp_offset_and_the_joint_torques_are_read_back_through_the_registers() -> None:
    """getTCPOffset() is what setTcp() set; getJointTorques() is what the arm's physics says its joints
    bear beyond its own dynamics (cell.robot.backends.joint_torques)."""
    ur, sim = URArm("r1", arm_model("ur5e")), Arm()
    ctl = control(ur)
    beyond = np.array([0.5, -1.25, 2.0, 0.0, 0.125, -0.75])
    ur.torques = lambda: (np.ones(6), beyond)
    tcp = [0.0, 0.01, 0.15, 0.0, 0.0, 0.3]
    for cmd, args in ((Cmd.SET_TCP, tcp), (Cmd.NO_CMD, []), (Cmd.GET_TCP_OFFSET, [])):
        ur.int_in[0] = cmd
        ur.double_in[: len(args)] = args
        sim.run(ctl.step, 1)
    assert ur.double_out[:6] == tcp
    ur.int_in[0] = Cmd.GET_JOINT_TORQUES  # (a realtime command: answered ready at once)
    sim.run(ctl.step, 1)
    assert ur.double_out[:6] == beyond.tolist() and ur.int_out[0] == READY and ctl.ended is None
