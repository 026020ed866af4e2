"""The URScript programs an emulated arm runs, one tick at a time (sans IO).

An arm runs one program at a time, like a UR: by default the cell's datagram program (the paper's
URCap daemon: the data plane's commands drive it); a script sent to its client interfaces takes the
arm over (cell.ur.server) and a Runner here runs it, telling the drives each tick what velocity to
hold.  When the runner ends (its last line, a stop, a fault) the arm goes back to the datagram program.

RtdeControl serves ur_rtde's control script natively: the script's main loop, read from the script
ur_rtde uploads, is a register protocol over RTDE: the client writes a command number into input
integer register 0 (+ the script's offset) and its arguments into the input double registers; the
script answers in output integer register 0 (1: ready for a command, 2: done with it), register 1
(a query's flag), register 2 (asynchronous progress) and the output double registers (a query's
pose or joints).  Real-time commands (servoJ, speedJ, speedL) are taken every tick and answered
`ready` at once; the others run to their end and answer `done`, and the client clears the command
(0) before the next.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import Enum, IntEnum

import numpy as np

from cell.robot.kinematics import Unreachable
from cell.ur.arm import SafetyMode, URArm
from cell.ur.motion import STEADY_RAD_S, Motion, MoveJ, MoveL, Servo, Speed, SpeedL
from cell.ur.urscript import END_LOOP, Call, Pose, Script


@dataclass(frozen=True, slots=True)
class Message:
    """What a program says on the primary interface: a text (textmsg, popup), a runtime exception, an
    error code (the controller's own report, as C209A0 for a protective stop) or a key message (a
    program started or stopped)."""

    text: str
    line: int = -1  # >= 0: a runtime exception at this line
    column: int = 0
    code: int = -1  # >= 0: an error code message with this code (argument 0)
    key: str = ""  # a key message with this title (the text is its argument: a program's name)


# what the controller reports as a protective stop begins (UR's error code C209A0)
PROTECTIVE_STOP = Message("A protective stop was triggered", code=209)
# calls a program may make in one tick: a loop that takes no time (no sleep, sync or motion) ends
# with a runtime exception instead of holding the tick
CALLS_PER_TICK = 10_000


class SocketState(Enum):
    OPENING = "opening"
    OPEN = "open"
    FAILED = "failed"
    CLOSED = "closed"


@dataclass(eq=False, slots=True)
class ProgramSocket:
    """A socket a program opened (socket_open): the server connects it (from the arm's address) and
    sends its outbox; the program waits at its socket_open until it is OPEN or FAILED, as on a UR."""

    name: str
    host: str
    port: int
    timeout: float
    state: SocketState = SocketState.OPENING
    outbox: bytearray = field(default_factory=bytearray)


class Runner:
    """A program under way.  step() returns the drives' velocity command for the next tick; once
    `ended` is not None the program is over ("" if it ran to its end, else why it stopped)."""

    def __init__(self, script: Script, arm: URArm) -> None:
        self.script, self.arm, self.tool = script, arm, arm.tool
        self.ended: str | None = None
        self.messages: list[Message] = []
        self.motion: Motion | None = None
        self.sockets: dict[str, ProgramSocket] = {}  # by name (the server opens, writes and closes them)
        # the tick it steps is the newest the process knows of (RobotGroup.live): a program stepped
        # through ticks its process was late for has not heard what its clients sent meanwhile
        self.live = True

    @property
    def name(self) -> str:
        return self.script.name

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        raise NotImplementedError

    def reference(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Its motion's reference (URArm.reference), if it has one."""
        return self.motion.reference() if self.motion is not None else None

    def servoing(self) -> Servo | None:
        """Its servoj, if that is what moves the arm: the drives close its loop (Drives.set_servo)."""
        return self.motion if isinstance(self.motion, Servo) and self.ended is None else None

    def _move(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        if self.motion is None:
            return np.zeros_like(q)
        return self.motion.step(q, qd, dt)


# --- straight-line programs ------------------------------------------------------------------------


class LineRunner(Runner):
    """movej, movel, speedj, servoj, stopj/l, sleep, sync, outputs, messages and sockets, one after
    another, in `while True:` loops or not."""

    def __init__(self, script: Script, arm: URArm) -> None:
        super().__init__(script, arm)
        self.calls = list(script.calls)
        self.at = 0
        self.wait = 0.0  # time left on the current call (sleep, speedj's t, servoj's t)
        self.started = False
        self.fresh = False  # the current call has not had a tick yet (a motion takes one at least)

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        calls = 0
        while self.ended is None:
            if self.at >= len(self.calls):
                self.ended = ""
                break
            call = self.calls[self.at]
            calls += 1
            if calls > CALLS_PER_TICK:  # (a loop of calls that take no time: it would hold the tick)
                reason = f"a loop ran {CALLS_PER_TICK} calls in one tick: it takes no time (add sync())"
                self.messages.append(Message(reason, call.line))
                self.ended = f"line {call.line}: {reason}"
                break
            if call.name == END_LOOP:
                self.at = int(call.args["to"])  # type: ignore[call-overload]  # (parse's own index)
                continue
            if not self.started:
                self.started, self.fresh = True, True
                try:
                    self._begin(call, q, qd)
                except Unreachable as exc:
                    if call.name == "movel":  # (a line the joints cannot follow: a UR protective-stops;
                        # movej's pose has no joints at all: get_inverse_kin raises, a runtime exception)
                        self.messages.append(Message(f"{call.name}: {exc.reason}"))
                        self.arm.safety_mode = SafetyMode.PROTECTIVE_STOP
                        self.messages.append(PROTECTIVE_STOP)
                    else:
                        self.messages.append(Message(f"{call.name}: {exc.reason}", call.line))
                    self.ended = f"line {call.line}: {exc.reason}"
                    break
            if self._running(call, dt):
                self.fresh = False
                return self._move(q, qd, dt)
            self.at, self.started = self.at + 1, False
        return np.zeros_like(q)

    def _begin(self, call: Call, q: np.ndarray, qd: np.ndarray) -> None:
        a = call.args
        arm, model = self.arm, self.tool.arm
        if call.name == "movej":
            target = a["q"]
            goal = (
                self.tool.ik_pose(np.array(target.v), q)
                if isinstance(target, Pose)
                else _joints(target, call)
            )
            self.motion = MoveJ(q, goal, _float(a["v"]), _float(a["a"]), model)
        elif call.name == "movel":
            target = a["pose"]
            goal = np.array(target.v) if isinstance(target, Pose) else self.tool.fk(_joints(target, call))
            self.motion = MoveL(q, goal, _float(a["v"]), _float(a["a"]), self.tool)
        elif call.name == "speedj":
            self.motion = Speed(qd, _joints(a["qd"], call), _float(a["a"]))
            self.wait = _float(a["t"])
        elif call.name == "servoj":
            if not isinstance(self.motion, Servo):
                self.motion = Servo(q)
            t = _float(a["t"])
            self.motion.set(_joints(a["q"], call), t, _float(a["lookahead_time"]))
            self.wait = t
        elif call.name in ("stopj", "stopl"):
            self.motion = Speed(qd, np.zeros_like(q), _float(a["a"]), stop=True)
        elif call.name == "sleep":
            self.wait = _float(a["t"])
        elif call.name == "sync":
            self.wait = 1e-9
        elif call.name == "set_standard_digital_out":
            n = int(a["n"])  # type: ignore[call-overload]  # any literal of the script: int() checks it
            if not 0 <= n <= 7:
                raise Unreachable(f"standard digital output {n} does not exist (0-7)")
            bit = 1 << n
            arm.digital_out = (arm.digital_out | bit) if a["b"] else (arm.digital_out & ~bit)
        elif call.name == "textmsg":
            self.messages.append(Message(f"{a['s1']}{a['s2']}"))
        elif call.name == "popup":
            arm.popup = str(a["s"])
            self.messages.append(Message(f"popup: {a['s']}"))
        elif call.name == "protective_stop":  # (the arm stops; the program ends, as on a UR)
            arm.safety_mode = SafetyMode.PROTECTIVE_STOP
            self.messages.append(PROTECTIVE_STOP)
            self.ended = "a protective stop (protective_stop())"
        elif call.name == "socket_open":
            name = str(a["socket_name"])
            old = self.sockets.get(name)
            if old is not None:  # (a name opened again: the old one closes, as on a UR)
                old.state = SocketState.CLOSED
            port = int(a["port"])  # type: ignore[call-overload]  # any literal of the script: int() checks it
            if not 0 < port < 65536:
                raise Unreachable(f"socket_open: port {port} is not a TCP port")
            self.sockets[name] = ProgramSocket(name, str(a["address"]), port, max(_float(a["timeout"]), 0.0))
        elif call.name in ("socket_send_string", "socket_send_line"):
            sock = self.sockets.get(str(a["socket_name"]))
            if sock is not None and sock.state == SocketState.OPEN:
                text = str(a["str"]) + ("\n" if call.name == "socket_send_line" else "")
                sock.outbox += text.encode()
        elif call.name == "socket_close":
            sock = self.sockets.get(str(a["socket_name"]))
            if sock is not None:
                sock.state = SocketState.CLOSED

    def _running(self, call: Call, dt: float) -> bool:
        """Whether the call goes on for another tick."""
        if call.name in ("movej", "movel", "stopj", "stopl"):
            m = self.motion
            if m is not None and m.done and m.error:
                self.messages.append(Message(f"{call.name}: {m.error}", call.line))
            return m is not None and (not m.done or self.fresh)
        if call.name == "socket_open":  # (it waits to be connected, or to fail)
            return self.sockets[str(call.args["socket_name"])].state == SocketState.OPENING
        if self.wait > 0:
            self.wait -= dt
            return True
        return False


def _float(v: object) -> float:
    return float(v)  # type: ignore[arg-type]  # any literal of the script: float() checks it


def _joints(v: object, call: Call) -> np.ndarray:
    if isinstance(v, list) and len(v) == 6:
        return np.array(v, np.float64)
    raise Unreachable(f"{call.name}() wants 6 joint values, got {v!r}")


# --- ur_rtde's control script ----------------------------------------------------------------------


class Cmd(IntEnum):
    """ur_rtde's command numbers (RTDE::RobotCommand::Type), those this arm serves."""

    NO_CMD = 0
    MOVEJ = 1
    MOVEJ_IK = 2
    MOVEL = 3
    MOVEL_FK = 4
    SPEEDJ = 9
    SPEEDL = 10
    SERVOJ = 11
    SPEED_STOP = 15
    SERVO_STOP = 16
    SET_PAYLOAD = 17
    SET_TCP = 29
    GET_INVERSE_KINEMATICS_ARGS = 30
    PROTECTIVE_STOP = 31
    STOPL = 33
    STOPJ = 34
    SET_WATCHDOG = 35
    GET_JOINT_TORQUES = 38
    GET_TCP_OFFSET = 40
    GET_FORWARD_KINEMATICS_DEFAULT = 43
    GET_FORWARD_KINEMATICS_ARGS = 44
    GET_INVERSE_KINEMATICS_DEFAULT = 46
    IS_STEADY = 47
    WATCHDOG = 99
    STOP_SCRIPT = 255


# taken every tick and answered `ready` at once (the script's list; those this arm does not serve
# are refused like any other it does not)
REALTIME = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
READY, DONE = 1, 2
CLIENT_GONE_S = 0.5  # no RTDE session has held the control script's register this long: it ends


class RtdeControl(Runner):
    """ur_rtde's control script, its register protocol served natively."""

    def __init__(self, script: Script, arm: URArm) -> None:
        super().__init__(script, arm)
        self.oi, self.of = script.reg_offset_int, script.reg_offset_float
        self.cmd_field = f"input_int_register_{self.oi}"
        self.executing = False
        self.blocking: Motion | None = None  # a synchronous command's motion, answered `done` at its end
        self.async_move: Motion | None = None
        self.wr_count = 0
        self.op_id = 0
        self.watchdog_s = 0.0
        self.commanded = False  # an RTDE client has held the command register
        self.unowned_since: float | None = None  # (clock s) since when none has held it
        self.clock = time.monotonic  # (its watchdogs' time: a test sets its own)
        self._progress(-1)
        self._out_int(0, READY)

    # registers, with the script's offsets
    def _int(self, i: int) -> int:
        return self.arm.int_in[self.oi + i]

    def _dbl(self, i: int, n: int = 1) -> np.ndarray:
        return np.array(self.arm.double_in[self.of + i : self.of + i + n])

    def _out_int(self, i: int, v: int) -> None:
        self.arm.int_out[self.oi + i] = v

    def _out_dbl(self, i: int, values: np.ndarray) -> None:
        self.arm.double_out[self.of + i : self.of + i + len(values)] = [float(x) for x in values]

    def _progress(self, value: int) -> None:
        """The asynchronous progress register as ur_rtde 1.6 reads it: bits 24-30 the operation's id,
        16-22 a write count, 15 running, 0-14 the progress."""
        self.wr_count = (self.wr_count + 1) % 128
        if value == 0:
            self.op_id = (self.op_id + 1) % 128
        reg = self.wr_count * 65536 + self.op_id * 16777216
        if value >= 0:
            reg += (value & 0x7FFF) + 32768
        self._out_int(2, reg)

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        arm = self.arm
        owner = arm.owner(self.cmd_field)
        if owner is not None:
            self.commanded, self.unowned_since = True, None
        elif self.commanded:  # its client went away: it stands, and the script stops as its RTDE
            now = self.clock()  # watchdog would, unless a client takes the register again
            if self.unowned_since is None:  # within CLIENT_GONE_S (ur_rtde's reuploadScript()
                self.unowned_since = now  # connects anew after sending the script again)
            elif now - self.unowned_since > CLIENT_GONE_S:
                self.ended = "the RTDE client driving the control script disconnected"
            return np.zeros_like(q)
        if self.watchdog_s and self.clock() - arm.written.get(self.cmd_field, 0.0) > self.watchdog_s:
            ms = self.watchdog_s * 1000
            self.ended = f"the RTDE watchdog on {self.cmd_field}: no input for {ms:.0f} ms"
            return np.zeros_like(q)
        if self.blocking is not None:
            if self.blocking.done:
                self.blocking = None
                self._out_int(0, DONE)
        else:
            cmd = self._int(0)
            if cmd in REALTIME:
                self._process(cmd, q, qd)
                if self.ended is None:  # (a command that ended the script is not acknowledged: the
                    self._out_int(0, READY)  # client's call fails, as on a UR whose script died)
            elif cmd == 0:
                self.executing = False
                self._out_int(0, READY)
            elif not self.executing:
                self.executing = True
                self._process(cmd, q, qd)
                if self.blocking is None and self.ended is None:
                    self._out_int(0, DONE)
        if self.ended is not None:
            return np.zeros_like(q)
        v = self._move(q, qd, dt)
        m = self.motion
        if m is not None and m.done:  # (said once: the arm stands until the next command)
            if m is self.async_move:
                self.async_move = None
                self._progress(-1)
            if m.error:
                self.messages.append(Message(f"rtde_control: {m.error}"))
            self.motion = None
        return v

    def _start(self, motion: Motion) -> None:
        """A move, synchronous (answered at its end) or asynchronous (input integer register 1 = 1)."""
        self.motion = motion
        if self._int(1) == 1:
            self.async_move = motion
            self._progress(0)
        else:
            if self.async_move is not None:
                self.async_move = None
                self._progress(-1)
            self.blocking = motion

    def _stop(self, qd: np.ndarray, a: float) -> None:
        if self.async_move is not None:
            self.async_move = None
            self._progress(-1)
        self.motion = self.blocking = Speed(qd, np.zeros_like(qd), a, stop=True)

    def _process(self, cmd: int, q: np.ndarray, qd: np.ndarray) -> None:
        tool, model = self.tool, self.tool.arm
        try:
            if cmd in (Cmd.MOVEJ, Cmd.MOVEJ_IK):
                target = self._dbl(0, 6)
                goal = tool.ik_pose(target, q) if cmd == Cmd.MOVEJ_IK else target
                self._start(MoveJ(q, goal, float(self._dbl(6)[0]), float(self._dbl(7)[0]), model))
            elif cmd in (Cmd.MOVEL, Cmd.MOVEL_FK):
                target = self._dbl(0, 6)
                goal = tool.fk(target) if cmd == Cmd.MOVEL_FK else target
                self._start(MoveL(q, goal, float(self._dbl(6)[0]), float(self._dbl(7)[0]), tool))
            elif cmd == Cmd.SPEEDJ:
                qd_goal, a = self._dbl(0, 6), float(self._dbl(6)[0])
                if isinstance(self.motion, Speed) and not self.motion.stop:
                    self.motion.set(qd_goal, a)
                else:
                    self.motion = Speed(qd, qd_goal, a)
            elif cmd == Cmd.SPEEDL:
                xd, a = self._dbl(0, 6), float(self._dbl(6)[0])
                if isinstance(self.motion, SpeedL):
                    self.motion.set(xd, a)
                else:
                    self.motion = SpeedL(tool, q, qd, xd, a)
            elif cmd == Cmd.SERVOJ:
                if not isinstance(self.motion, Servo):
                    self.motion = Servo(q)
                self.motion.set(self._dbl(0, 6), float(self._dbl(8)[0]), float(self._dbl(9)[0]))
            elif cmd in (Cmd.SPEED_STOP, Cmd.SERVO_STOP, Cmd.STOPJ, Cmd.STOPL):
                self._stop(qd, float(self._dbl(0)[0]))
            elif cmd == Cmd.SET_PAYLOAD:
                self.arm.payload = float(self._dbl(0)[0])
                cog = self._dbl(1, 3)
                if cog.any():
                    self.arm.cog = (float(cog[0]), float(cog[1]), float(cog[2]))
            elif cmd == Cmd.SET_TCP:
                tool.set_tcp(self._dbl(0, 6))
            elif cmd == Cmd.GET_INVERSE_KINEMATICS_DEFAULT:
                self._out_dbl(0, tool.ik_pose(self._dbl(0, 6), q))
            elif cmd == Cmd.GET_INVERSE_KINEMATICS_ARGS:
                self._out_dbl(0, tool.ik_pose(self._dbl(0, 6), self._dbl(6, 6)))
            elif cmd == Cmd.GET_FORWARD_KINEMATICS_DEFAULT:
                self._out_dbl(0, tool.fk(q))
            elif cmd == Cmd.GET_FORWARD_KINEMATICS_ARGS:
                self._out_dbl(0, tool.fk(self._dbl(0, 6), self._dbl(6, 6)))
            elif cmd == Cmd.GET_JOINT_TORQUES:  # (get_joint_torques(): beyond the arm's own dynamics)
                self._out_dbl(0, self.arm.torques()[1])
            elif cmd == Cmd.GET_TCP_OFFSET:
                self._out_dbl(0, tool.tcp)
            elif cmd == Cmd.IS_STEADY:
                moving = self.motion is not None and not self.motion.done
                steady = not moving and float(np.abs(qd).max()) < STEADY_RAD_S
                self._out_int(1, int(steady))
            elif cmd == Cmd.PROTECTIVE_STOP:
                self.arm.safety_mode = SafetyMode.PROTECTIVE_STOP
                self.ended = "a protective stop (triggerProtectiveStop)"
            elif cmd == Cmd.SET_WATCHDOG:
                hz = float(self._dbl(0)[0])
                self.watchdog_s = 1.0 / hz if hz > 0 else 0.0
            elif cmd == Cmd.WATCHDOG:
                pass  # (the write itself kicks it)
            elif cmd == Cmd.STOP_SCRIPT:
                self.ended = ""
            else:
                name = f"command {cmd}"
                self.messages.append(
                    Message(f"rtde_control: {name} is not emulated by this arm; the script stops", 0)
                )
                self.ended = f"ur_rtde {name} is not emulated"
        except Unreachable as exc:
            # a UR's script dies on an IK failure (get_inverse_kin raises): so does this one
            self.messages.append(Message(f"rtde_control: {exc.reason}", 0))
            self.ended = exc.reason


# --- the cell's daemon program ---------------------------------------------------------------------


class DaemonProgram(Runner):
    """The daemon's program (cell.ur.daemon.script), served natively: each cycle, the velocities in
    the input double registers approached within each joint's limits; the window number and a
    heartbeat written back; after `watchdog` cycles with the same window number, a stop."""

    def __init__(self, script: Script, arm: URArm) -> None:
        super().__init__(script, arm)
        cfg = script.settings  # (parse() checked them)
        registers, watchdog = cfg["registers"], cfg["watchdog"]
        assert isinstance(registers, float) and isinstance(watchdog, float)
        self.first = int(registers)
        self.watchdog = int(watchdog)
        self.v_max = np.array(cfg["v_max"])
        self.a_max = np.array(cfg["a_max"])
        self.window = arm.int_in[self.first]
        self.idle = 0
        self.beat = 0
        self.qd: np.ndarray | None = None  # the velocity it commands (the script's qd)

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        arm, r = self.arm, self.first
        taken = arm.int_in[r]
        if taken != self.window:
            self.window, self.idle = taken, 0
        elif self.idle < self.watchdog:
            self.idle += 1
        goal = np.array(arm.double_in[r : r + 6]) if self.idle < self.watchdog else np.zeros_like(q)
        goal = np.minimum(np.maximum(goal, -self.v_max), self.v_max)
        now = qd.copy() if self.qd is None else self.qd
        step = self.a_max * 0.002  # (get_steptime(): the controller's cycle, whatever the tick's dt)
        self.qd = now + np.minimum(np.maximum(goal - now, -step), step)
        self.beat = self.beat + 1 if self.beat < 1_000_000_000 else 1
        arm.int_out[r], arm.int_out[r + 1] = self.window, self.beat
        return self.qd


RUNNERS: dict[str, type[Runner]] = {
    "rtde_control": RtdeControl,
    "lines": LineRunner,
    "cell_daemon": DaemonProgram,
}


def runner(script: Script, arm: URArm) -> Runner:
    """The runner of a parsed program."""
    return RUNNERS[script.kind](script, arm)
