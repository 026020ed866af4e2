"""UR's external_control program, the one UR's client library (and so UR's ROS 2 driver) sends, served
natively (sans IO): the wire formats of its three sockets and the program's main loop, one tick at a
time.

The program (URCL's resources/external_control.urscript, sent headless to the primary interface
wrapped in `def externalControl():`) connects back to the client: the trajectory point interface
(50003), the script command interface (50004) and the reverse interface (50001), in that order.
Every message is big-endian int32s, reals scaled by MULT_jointstate (1e6) and times by MULT_time:

- reverse (client -> arm), 8 ints: the read timeout (ms) for the next message, six values (joint
  positions, velocities, a twist or a pose, by the mode; for trajectory forwarding the action and
  the point count), the control mode.  A message that does not come within its read timeout ends
  the program ("Socket timed out waiting for command on reverse_socket"), as does MODE_STOPPED;
- trajectory points (client -> arm), 21 ints: three blocks of six (target; qnear, via or spline
  velocities; v, a, has_qnear or spline accelerations), the time, the blend radius or spline type,
  the motion type; the arm answers each trajectory with one int: success, canceled or failure;
- script commands (client -> arm), 28 ints: the command and its arguments; tool contact answers an
  int on the same socket.

What this arm has no model of is refused in UR's way: force mode and tool contact end the program
with a runtime exception the client sees; direct torque control pops up what PolyScope 5.11 says of
it (it needs 5.23); optimove points pop up what 5.11 says (5.21 has them).  Freedrive is taken: no
hand guides the arm, so it stands.  movep runs as movel (one process move is a straight line at a
constant tool speed), movec on its circular arc.  Blend radii are not modelled: each point of a
movej/movel/movep/movec trajectory is reached and left from rest.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from cell.robot.kinematics import Unreachable
from cell.ur.arm import SafetyMode, URArm
from cell.ur.motion import KP, Motion, MoveC, MoveJ, MoveL, Servo, Speed, SpeedL, pull
from cell.ur.program import PROTECTIVE_STOP, RUNNERS, LineRunner, Message, Runner
from cell.ur.urscript import EXTERNAL_SOCKETS as SOCKETS
from cell.ur.urscript import Call, Script


class Mode(IntEnum):
    STOPPED = -2
    UNINITIALIZED = -1
    IDLE = 0
    SERVOJ = 1
    SPEEDJ = 2
    FORWARD = 3
    SPEEDL = 4
    POSE = 5
    FREEDRIVE = 6
    TOOL_IN_CONTACT = 7
    TORQUE = 8


class TrajectoryAction(IntEnum):
    CANCEL = -1
    RECEIVE = 1
    STREAM_START = 2
    STREAM_END = 3


class MotionType(IntEnum):
    MOVEJ = 0
    MOVEL = 1
    MOVEP = 2
    MOVEC = 3
    OPTIMOVEJ = 4
    OPTIMOVEL = 5
    MOVEJ_POSE = 6
    MOVEL_JOINT = 7
    MOVEP_JOINT = 8
    MOVEC_JOINT = 9
    MOVEC_JOINT_POSE = 10
    MOVEC_POSE_JOINT = 11
    OPTIMOVEJ_POSE = 12
    OPTIMOVEL_JOINT = 13
    SPLINE = 51


class Result(IntEnum):
    SUCCESS = 0
    CANCELED = 1
    FAILURE = 2


class Command(IntEnum):
    ZERO_FTSENSOR = 0
    SET_PAYLOAD = 1
    SET_TOOL_VOLTAGE = 2
    START_FORCE_MODE = 3
    END_FORCE_MODE = 4
    START_TOOL_CONTACT = 5
    END_TOOL_CONTACT = 6
    SET_FRICTION_COMPENSATION = 7
    FT_RTDE_INPUT_ENABLE = 8
    SET_GRAVITY = 9
    SET_TCP_OFFSET = 10
    SET_FRICTION_SCALES = 11
    SET_TARGET_PAYLOAD = 12


MULT = 1_000_000  # MULT_jointstate and MULT_time as UR's client library fills them in
SPLINE_CUBIC, SPLINE_QUINTIC = 1, 2
FREEDRIVE_START, FREEDRIVE_STOP = 1, -1
TOOL_CONTACT_CANCELED = 1
REVERSE = struct.Struct(">8i")
POINT = struct.Struct(">21i")
COMMAND = struct.Struct(">28i")
RESULT = struct.Struct(">i")
STREAMING_SENTINEL = 2147483647
MOVECS = (MotionType.MOVEC, MotionType.MOVEC_JOINT, MotionType.MOVEC_POSE_JOINT, MotionType.MOVEC_JOINT_POSE)
STOPJ_ACCELERATION = 4.0
SPEEDJ_ACCELERATION = 40.0  # the program's speedThread: speedj(qd, 40.0, steptime)
MAX_JOINT_SPEED = 6.283185  # rad/s: the script's, for the last spline segment's slowing down
MAX_DECELERATION = 15.0  # rad/s^2: its max_deceleration
DECELERATION_TIME_S = MAX_JOINT_SPEED / MAX_DECELERATION
JOINT_IGNORE_SPEED = 20.0  # rad/s: a servo target or spline point needing more is ignored
STEP_S = 0.002  # get_steptime() of an e-Series
FIRST_POINT_TIMEOUT_S = 0.5  # the trajectory thread's wait for a point while the arm stands


@dataclass(frozen=True, slots=True)
class Settings:
    """What the client filled into the script: where to connect back, its scales, servoj's tuning."""

    host: str
    ports: dict[str, int]  # socket name -> port
    mult_joint: float
    mult_time: float
    lookahead: float
    gain: float
    # the output double register the script writes its spline time to (UR's client library's
    # spline tests uncomment that line), -1 if none
    spline_register: int = -1
    sends_canceled: bool = True  # whether the script answers a canceled trajectory (a client may strip it)


def read_settings(script: Script) -> Settings:
    s = script.settings
    host = s["host"]
    assert isinstance(host, tuple)
    return Settings(
        ".".join(str(int(b)) for b in host),
        {name: int(s[f"port_{name}"]) for name in SOCKETS},  # type: ignore[arg-type]
        float(s["mult_joint"]),  # type: ignore[arg-type]
        float(s["mult_time"]),  # type: ignore[arg-type]
        float(s["lookahead"]),  # type: ignore[arg-type]
        float(s["gain"]),  # type: ignore[arg-type]
        int(s.get("spline_register", -1)),  # type: ignore[arg-type]
        bool(s.get("sends_canceled", 1.0)),
    )


def client_program(host: str, ports: dict[str, int], lookahead: float = 0.03, gain: float = 2000) -> str:
    """A program as UR's client library sends it headless to the primary interface, reduced to what
    this arm reads of it (its multipliers, servoj's tuning, where to connect back): for clients of
    the project's own (cell bench ur, the tests) that have no copy of UR's script."""
    p = ports
    body = f"""steptime = get_steptime()
MULT_jointstate = {MULT}
MULT_time = {MULT}
thread servoThread():
  servoj(q, t=steptime, lookahead_time={lookahead}, gain={gain})
end
def cancelTrajectory():
  socket_send_int(TRAJECTORY_RESULT_CANCELED, "trajectory_socket")
end
traj_flag = connect_socket_with_retry("{host}", {p["trajectory_socket"]}, "trajectory_socket")
com_flag = connect_socket_with_retry("{host}", {p["script_command_socket"]}, "script_command_socket")
rev_flag = connect_socket_with_retry("{host}", {p["reverse_socket"]}, "reverse_socket")
while control_mode > MODE_STOPPED:
  params_mult = socket_read_binary_integer(8, "reverse_socket", read_timeout)
end
# NODE_CONTROL_LOOP_ENDS"""
    return (
        "stop program\ndef externalControl():\n"
        + "".join(f"\t{line}\n" for line in body.splitlines())
        + "end\n"
    )


class _Reader:
    """Fixed-size messages out of a byte stream."""

    def __init__(self, shape: struct.Struct) -> None:
        self.shape, self.buf = shape, bytearray()
        self.messages: deque[tuple[int, ...]] = deque()

    def feed(self, data: bytes) -> None:
        self.buf += data
        n = len(self.buf) // self.shape.size
        for i in range(n):
            self.messages.append(self.shape.unpack_from(self.buf, i * self.shape.size))
        del self.buf[: n * self.shape.size]


class Spline(Motion):
    """One spline segment as the program runs it (cubicSplineRun, quinticSplineRun, jointSplineRun):
    a polynomial in time from where the arm is, its start velocity and acceleration the last
    segment's end ones, to the point's position, velocity (and acceleration), stepped a control step
    at a time; on the trajectory's last point, once a joint would be too fast to stop at 15 rad/s^2
    by the end, the segment's time is scaled down to a stop, following its positions.  The drives get
    its (scaled) velocity and a pull onto its position."""

    def __init__(self, q0: np.ndarray, qd0: np.ndarray, qdd0: np.ndarray, q1: np.ndarray, qd1: np.ndarray,
                 qdd1: np.ndarray | None, duration: float, last: bool) -> None:  # fmt: skip
        T = duration
        self.q0, self.T, self.last, self.quintic = q0.copy(), T, last, qdd1 is not None
        self.t = 0.0  # the script's splineTimerTraveled
        self.scale = 1.0  # its scaling_factor
        self.slowing, self.slowing_total = False, 0.0
        if qdd1 is None:  # cubic
            zero = np.zeros_like(q0)
            self.c = [
                qd0,
                (-3 * q0 + 3 * q1 - 2 * qd0 * T - qd1 * T) / T**2,
                (2 * q0 - 2 * q1 + qd0 * T + qd1 * T) / T**3,
                zero,
                zero,
            ]
        else:  # quintic
            T2 = T * T
            self.c = [
                qd0,
                0.5 * qdd0,
                (-20 * q0 + 20 * q1 - 3 * qdd0 * T2 + qdd1 * T2 - 12 * qd0 * T - 8 * qd1 * T) / (2 * T**3),
                (30 * q0 - 30 * q1 + 3 * qdd0 * T2 - 2 * qdd1 * T2 + 16 * qd0 * T + 14 * qd1 * T)
                / (2 * T**4),
                (-12 * q0 + 12 * q1 - qdd0 * T2 + qdd1 * T2 - 6 * qd0 * T - 6 * qd1 * T) / (2 * T**5),
            ]
        self.qd_last, self.qdd_last = qd0.copy(), qdd0.copy()  # the script's spline_qd, spline_qdd

    def position(self, t: float) -> np.ndarray:
        c = self.c
        return self.q0 + c[0] * t + c[1] * t**2 + c[2] * t**3 + c[3] * t**4 + c[4] * t**5

    def velocity(self, t: float) -> np.ndarray:
        c = self.c
        return c[0] + 2 * c[1] * t + 3 * c[2] * t**2 + 4 * c[3] * t**3 + 5 * c[4] * t**4

    def acceleration(self, t: float) -> np.ndarray:
        c = self.c
        return 2 * c[1] + 6 * c[2] * t + 12 * c[3] * t**2 + 20 * c[4] * t**3

    def reference(self) -> tuple[np.ndarray, np.ndarray]:
        return self.position(self.t), self.qd_last

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        left = self.T - self.t
        if left > STEP_S:  # (the script's main loop: whole steps)
            if self.last and left <= DECELERATION_TIME_S:
                if not self.slowing:
                    x = DECELERATION_TIME_S - (left - STEP_S)
                    peek = self.velocity(self.t + STEP_S)
                    self.slowing = bool((np.abs(peek) > MAX_JOINT_SPEED - x * MAX_DECELERATION).any())
                    if self.slowing:
                        self.slowing_total = left + STEP_S
                if self.slowing:
                    self.scale = left / self.slowing_total
            self.t += STEP_S * self.scale
            step = 1.0
        elif self.slowing and left >= 1e-5:  # (approaching zero velocity slowly)
            self.scale = left / self.slowing_total
            self.t += STEP_S * self.scale
            step = 1.0
        else:  # (the last part, less than a step)
            if self.slowing:
                self.scale = 0.0
            step = left / dt if dt > 0 else 0.0
            self.t = self.T
            self.done = True
        self.qd_last = self.velocity(self.t) * self.scale
        self.qdd_last = self.acceleration(self.t)
        if self.done and self.scale == 0.0:
            return np.zeros_like(q)
        return self.qd_last * step + KP * (self.position(self.t) - q)


class Stop(Motion):
    """stopj on the program's target: the target's velocity ramped to zero at `a`, its position moving
    on with it, the drives told that velocity and pulled onto that position (an arm that lagged its
    target, held back by its joint limits, still comes to stand where the target did, as a UR's)."""

    def __init__(self, q_ref: np.ndarray, v_ref: np.ndarray, a: float, a_max: np.ndarray) -> None:
        self.q_ref, self.v, self.a, self.a_max = q_ref.copy(), v_ref.copy(), a, a_max

    def reference(self) -> tuple[np.ndarray, np.ndarray]:
        return self.q_ref, self.v

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        dv = -self.v
        big = float(np.abs(dv).max())
        if big > self.a * dt:
            dv = dv * (self.a * dt / big)
        self.v = self.v + dv
        self.q_ref = self.q_ref + self.v * dt
        self.done = not self.v.any()
        return self.v + pull(self.q_ref - q, self.a_max)


class ExternalControl(Runner):
    """URCL's external_control program: its main loop (the reverse interface), its trajectory thread
    and its script command thread, stepped once a tick.  The server feeds each socket's bytes in
    (feed) and sends `outbox`; until `connected` the program waits at its socket_open calls."""

    def __init__(self, script: Script, arm: URArm) -> None:
        super().__init__(script, arm)
        self.settings = read_settings(script)
        self.connected = False
        self.readers = {
            "reverse_socket": _Reader(REVERSE),
            "trajectory_socket": _Reader(POINT),
            "script_command_socket": _Reader(COMMAND),
        }
        self.closed: set[str] = set()  # sockets the client closed
        self.outbox: dict[str, bytearray] = {name: bytearray() for name in SOCKETS}
        self.mode = Mode.UNINITIALIZED
        self.read_timeout = 0.0  # s; 0: the next read blocks (the first)
        self.since_message = 0.0
        self.servo: Servo | None = None
        self.servo_new = False
        # the trajectory thread
        self.points_left = 0
        self.streaming = False
        self.traj_streamed = False  # (was_streaming_at_start)
        self.traj_running = False
        self.traj_first = True
        self.traj_moving = False
        self.traj_wait = 0.0
        self.spline_qd: np.ndarray | None = None
        self.spline_qdd: np.ndarray | None = None
        self.last_v = np.zeros(arm.model.dof)  # the target's velocity last tick
        self.q_now = np.zeros(arm.model.dof)  # the joints as the last tick found them
        self.messages.append(Message(f"ExternalControl: steptime={STEP_S}"))
        self.tail: LineRunner | None = None  # once its control loop is over: the code after it

    # --- I/O, from the server -------------------------------------------------------------------

    def feed(self, name: str, data: bytes) -> None:
        self.readers[name].feed(data)

    def lost(self, name: str) -> None:
        """The client closed one of the program's sockets: its reads fail from now on."""
        self.closed.add(name)

    def _send(self, name: str, value: int) -> None:
        self.outbox[name] += RESULT.pack(value)

    def _canceled(self) -> None:
        """TRAJECTORY_RESULT_CANCELED to the client, where the script says it (a client may strip it)."""
        if self.settings.sends_canceled:
            self._send("trajectory_socket", Result.CANCELED)

    # --- the program's loops ----------------------------------------------------------------------

    def reference(self) -> tuple[np.ndarray, np.ndarray] | None:
        return self.tail.reference() if self.tail is not None else super().reference()

    def servoing(self) -> Servo | None:
        if self.tail is not None:
            return self.tail.servoing()
        return self.servo if self.mode in (Mode.SERVOJ, Mode.POSE) and self.ended is None else None

    def step(self, q: np.ndarray, qd: np.ndarray, dt: float) -> np.ndarray:
        self.q_now = q
        if self.tail is not None:  # (the control loop is over: the program's last lines)
            v = self.tail.step(q, qd, dt)
            self.messages += self.tail.messages
            self.tail.messages.clear()
            self.ended = self.tail.ended
            return v
        if not self.connected:
            return np.zeros_like(q)
        self._script_commands()
        if self.ended is not None:
            return np.zeros_like(q)
        reverse = self.readers["reverse_socket"].messages
        if reverse:
            while reverse and self.ended is None:
                self._reverse(reverse.popleft(), q, qd)
            self.since_message = 0.0
        else:
            self.since_message += dt if self.live else 0.0  # (its messages wait unread too)
            if "reverse_socket" in self.closed or (
                self.read_timeout > 0 and self.since_message > self.read_timeout
            ):
                self.messages.append(
                    Message(
                        "Socket timed out waiting for command on reverse_socket. The script will exit now."
                    )
                )
                self.ended = (
                    "" if "reverse_socket" in self.closed else "the reverse interface's read timed out"
                )
                return np.zeros_like(q)
        if self.ended is not None:
            return np.zeros_like(q)
        if self.mode == Mode.SERVOJ or self.mode == Mode.POSE:
            assert self.servo is not None
            if not self.servo_new:  # extrapolate(): the last target moved on at the target speed
                self.servo.extrapolate(STEP_S)
            self.servo_new = False
            self.last_v = self.servo.step(q, qd, dt)
            return self.last_v
        if self.mode == Mode.FORWARD:
            self._trajectory(q, dt)
        v = self._move(q, qd, dt)
        ref = self.reference()
        self.last_v = v if ref is None else ref[1]  # (the target's velocity, not the pull onto it)
        if isinstance(self.motion, Spline) and self.settings.spline_register >= 0:
            self.arm.double_out[self.settings.spline_register] = self.motion.t  # (the tests' probe)
        return v

    def _reverse(self, msg: tuple[int, ...], q: np.ndarray, qd: np.ndarray) -> None:
        """One pass of the main loop over a message of the reverse interface."""
        s = self.settings
        timeout_ms, values, mode = msg[0], np.array(msg[1:7], np.float64) / s.mult_joint, msg[7]
        self.read_timeout = timeout_ms / 1000.0
        if mode not in Mode._value2member_map_:
            self.messages.append(Message(f"ExternalControl: unknown control mode {mode}, message ignored"))
            return
        new = Mode(mode)
        if new != self.mode:
            if self.mode == Mode.FORWARD:
                if self.points_left > 0 and self.traj_running:  # (a trajectory cut short: canceled)
                    self._drop_points(self.points_left)
                    self.points_left = 0
                    self._stopj()
                    self._canceled()
                self.traj_running = False
            self.mode = new
            if new in (Mode.SERVOJ, Mode.POSE):
                self.servo = Servo(q, extrapolates=True)
                self.messages.append(Message("ExternalControl: Starting servo thread"))
            elif new in (Mode.FORWARD, Mode.IDLE):
                self._stopj()
            elif new == Mode.STOPPED:
                self._stopj()
                self.messages.append(Message("ExternalControl: Stopping communication and control"))
                if self.script.tail:  # (its sockets close, then what the client appended runs)
                    stop = Call("stopj", {"a": STOPJ_ACCELERATION}, 0)
                    tail = Script(self.script.name, "lines", [stop, *self.script.tail])
                    self.tail = LineRunner(tail, self.arm)
                    self.tail.sockets = self.sockets
                else:
                    self.ended = ""
                return
            elif new == Mode.FREEDRIVE:  # (no hand guides it: it stands, as a UR's would)
                self._stopj()
            elif new == Mode.TORQUE:  # (what the script says on PolyScope < 5.23)
                self.arm.popup = "Torque control is only supported from software 5.23.0 and upwards."
                self.messages.append(Message(f"popup: {self.arm.popup}"))
                self._stopj()
        if self.mode in (Mode.SERVOJ, Mode.POSE):
            assert self.servo is not None
            target = values
            if self.mode == Mode.POSE:
                try:
                    target = self.tool.ik_pose(values, self.servo.target)
                except Unreachable as exc:
                    self._refuse(f"get_inverse_kin(): {exc.reason}")
                    return
            if self._within_limits(self.servo.target, target) or self._within_limits(q, target):
                self.servo.set(target, STEP_S, s.lookahead)
                self.servo_new = True
        elif self.mode == Mode.SPEEDJ:
            if isinstance(self.motion, Speed) and not self.motion.stop:
                self.motion.set(values, SPEEDJ_ACCELERATION)
            else:
                self.motion = Speed(qd, values, SPEEDJ_ACCELERATION)
        elif self.mode == Mode.SPEEDL:
            if isinstance(self.motion, SpeedL):
                self.motion.set(values, SPEEDJ_ACCELERATION)
            else:
                self.motion = SpeedL(self.tool, q, qd, values, SPEEDJ_ACCELERATION)
        elif self.mode == Mode.FORWARD:
            self._forward(int(msg[1]), int(msg[2]))
        elif self.mode == Mode.FREEDRIVE and msg[1] in (FREEDRIVE_START, FREEDRIVE_STOP):
            word = "Entering" if msg[1] == FREEDRIVE_START else "Leaving"
            self.messages.append(Message(f"{word} freedrive mode"))

    def _stopj(self) -> None:
        """stopj(4.0): from the target's velocity down to standing, on the target."""
        held = self.arm.reference
        q_ref = held[0] if held is not None else self.q_now
        self.motion = Stop(q_ref, self.last_v, STOPJ_ACCELERATION, self.tool.arm.limits.a_max)

    def _within_limits(self, start: np.ndarray, end: np.ndarray, t: float = STEP_S) -> bool:
        """targetWithinLimits: no joint faster than JOINT_IGNORE_SPEED to get there in t."""
        v = np.abs(np.asarray(end) - np.asarray(start)) / t
        if (v > JOINT_IGNORE_SPEED).any():
            j = int(np.argmax(v))
            self.messages.append(
                Message(
                    f"Velocity {v[j]:.6g} required in joint {j} to go from {start[j]:.6g} to {end[j]:.6g} "
                    f"within {t} seconds is exceeding the joint velocity limits. Ignoring commands until a "
                    "valid command is received."
                )
            )
            return False
        return True

    def _refuse(self, reason: str) -> None:
        """A runtime exception: the program ends, the client sees why."""
        self.messages.append(Message(reason, 0))
        self.ended = reason

    # --- trajectory forwarding ------------------------------------------------------------------

    def _forward(self, action: int, count: int) -> None:
        if action == TrajectoryAction.RECEIVE:
            self._start_trajectory(count, streaming=False)
        elif action == TrajectoryAction.STREAM_START:
            self._start_trajectory(STREAMING_SENTINEL, streaming=True)
        elif action == TrajectoryAction.STREAM_END and self.streaming:
            self.points_left = count - (STREAMING_SENTINEL - self.points_left)
            self.streaming = False
        elif action == TrajectoryAction.CANCEL:
            self.messages.append(Message("cancel received"))
            if self.streaming:
                self.points_left = count - (STREAMING_SENTINEL - self.points_left)
                self.streaming = False
            self._drop_points(max(self.points_left, 0))
            self.points_left = 0
            self.traj_running = False
            self._stopj()
            self._canceled()

    def _start_trajectory(self, count: int, streaming: bool) -> None:
        if self.points_left > 0:  # (the last one's unread points: clearTrajectoryPointsThread)
            self._drop_points(self.points_left)
        self.points_left, self.streaming, self.traj_streamed = count, streaming, streaming
        self.traj_running, self.traj_first, self.traj_moving = True, True, False
        self.traj_wait = 0.0
        self.spline_qd = self.spline_qdd = None
        self.motion = None
        if not streaming:
            self.messages.append(Message(f"Executing trajectory. Number of points: {count}"))

    def _drop_points(self, n: int) -> None:
        """clearTrajectoryPointsThread: the points of a trajectory that will not run, read and dropped."""
        points = self.readers["trajectory_socket"].messages
        for _ in range(min(n, len(points))):
            points.popleft()

    def _end_trajectory(self, result: Result) -> None:
        self.traj_running = False
        self._stopj()
        self._send("trajectory_socket", result)
        self.messages.append(Message(f"Trajectory finished with result {result.name}"))

    def _trajectory(self, q: np.ndarray, dt: float) -> None:
        """The trajectory thread: the next point once the last one is done."""
        if not self.traj_running:
            return
        if self.motion is not None and not self.motion.done:
            return
        if isinstance(self.motion, Spline):  # (the script's globals after the segment)
            self.spline_qd = self.motion.qd_last
            self.spline_qdd = self.motion.qdd_last if self.motion.quintic else None
        if self.motion is not None and self.motion.error:
            self._end_trajectory(Result.FAILURE)
            return
        if self.points_left <= 0:
            self._end_trajectory(Result.SUCCESS)
            return
        points = self.readers["trajectory_socket"].messages
        if not points:
            self.traj_wait += dt if self.live else 0.0  # (the points sent meanwhile wait unread too)
            # (as the script's read: 0.5 s while the arm stands, a step while it moves; a tick of
            # slack for the bytes that arrive between two ticks)
            limit = STEP_S + dt if self.traj_moving else FIRST_POINT_TIMEOUT_S
            if self.traj_wait > limit or "trajectory_socket" in self.closed:
                self.traj_wait = 0.0
                self.points_left -= 1
                if self.traj_streamed and not self.streaming and self.points_left < 0:
                    self.points_left = 0  # (STREAM_END came after the last point was taken: done)
                    return
                self.messages.append(Message("Receiving trajectory point failed!"))
                self._end_trajectory(Result.FAILURE)
            return
        self.traj_wait = 0.0
        raw = points.popleft()
        self.points_left -= 1
        last = self.points_left == 0
        try:
            result = self._point(raw, q, last)
        except Unreachable as exc:  # (as a UR's planner: the arm protective-stops)
            self.messages.append(Message(f"trajectory point: {exc.reason}"))
            self.arm.safety_mode = SafetyMode.PROTECTIVE_STOP
            self.messages.append(PROTECTIVE_STOP)
            result = Result.FAILURE
        self.traj_first = False
        if result is not None:
            self._end_trajectory(result)

    def _point(self, raw: tuple[int, ...], q: np.ndarray, last: bool) -> Result | None:
        """Start one point's motion; a result if the trajectory ends on it."""
        s = self.settings
        block = [np.array(raw[i : i + 6], np.float64) / s.mult_joint for i in (0, 6, 12)]
        t = raw[18] / s.mult_time
        kind = raw[20]
        v, a = block[2][0], block[2][1]
        if kind == MotionType.SPLINE:
            return self._spline(raw[19], block, t, q, last)
        self.spline_qd = self.spline_qdd = None
        self.traj_moving = False
        if kind in (MotionType.MOVEJ, MotionType.MOVEJ_POSE):
            goal = block[0]
            if kind == MotionType.MOVEJ_POSE:
                goal = self.tool.ik_pose(block[0], block[1] if block[2][2] else q)
            lim = self.tool.arm.limits
            if ((goal < lim.q_min) | (goal > lim.q_max)).any():
                j = int(np.argmax((goal < lim.q_min) | (goal > lim.q_max)))
                self.messages.append(
                    Message(f"movej: joint {j} target {goal[j]:.6g} rad is outside its range")
                )
                return Result.FAILURE
            v, a = _timed(goal - q, v, a, t)
            self.motion = MoveJ(q, goal, v, a, self.tool.arm)
        elif kind in (MotionType.MOVEL, MotionType.MOVEL_JOINT, MotionType.MOVEP, MotionType.MOVEP_JOINT):
            # (movep as movel: a single process move is a straight line at constant tool speed; the
            # blends between several are not modelled)
            joint = kind in (MotionType.MOVEL_JOINT, MotionType.MOVEP_JOINT)
            pose = self.tool.fk(block[0]) if joint else block[0]
            p0 = self.tool.fk(q)
            v, a = _timed(pose[:3] - p0[:3], v, a, t)
            self.motion = MoveL(q, pose, v, a, self.tool)
        elif kind in MOVECS:
            target, via = block[0], block[1]
            if kind in (MotionType.MOVEC_JOINT, MotionType.MOVEC_JOINT_POSE):
                target = self.tool.fk(target)
            if kind in (MotionType.MOVEC_JOINT, MotionType.MOVEC_POSE_JOINT):
                via = self.tool.fk(via)
            self.motion = MoveC(q, via, target, v, a, self.tool, fixed=block[2][2] == 1)
        elif kind in (
            MotionType.OPTIMOVEJ,
            MotionType.OPTIMOVEL,
            MotionType.OPTIMOVEJ_POSE,
            MotionType.OPTIMOVEL_JOINT,
        ):
            # (the script's own words on PolyScope < 5.21: a popup, and on to the next point)
            name = "Optimovej" if kind in (MotionType.OPTIMOVEJ, MotionType.OPTIMOVEJ_POSE) else "Optimovel"
            self.arm.popup = f"{name} is only supported from software 5.21.0 and upwards."
            self.messages.append(Message(f"popup: {self.arm.popup}"))
            self.motion = None
        else:
            name = MotionType(kind).name.lower() if kind in MotionType._value2member_map_ else f"type {kind}"
            self.messages.append(Message(f"trajectory point: {name} is not modelled by this emulated arm"))
            return Result.FAILURE
        return None

    def _spline(
        self, kind: int, block: list[np.ndarray], t: float, q: np.ndarray, last: bool
    ) -> Result | None:
        if t <= 0.0:
            if self.traj_first and t == 0.0 and float(np.linalg.norm(block[0] - q)) < 0.01:
                self.messages.append(Message("Ignoring first point with time 0"))
                if self.settings.spline_register >= 0:
                    self.arm.double_out[self.settings.spline_register] = 0.0
                self.motion = None
                return None
            self.messages.append(
                Message(
                    "Spline time shouldn't be zero as it would require infinite velocity to reach the "
                    "target. Canceling motion."
                )
            )
            return Result.CANCELED
        if kind not in (SPLINE_CUBIC, SPLINE_QUINTIC):
            self.messages.append(Message(f"Unknown spline type given: {kind}"))
            return Result.FAILURE
        if not self._within_limits(q, block[0], t):
            return Result.CANCELED
        zero = np.zeros_like(q)
        qd0 = zero if self.spline_qd is None else self.spline_qd
        qdd0 = zero if self.spline_qdd is None else self.spline_qdd
        end_qdd = block[2] if kind == SPLINE_QUINTIC else None
        self.motion = Spline(q, qd0, qdd0, block[0], block[1], end_qdd, t, last)
        self.traj_moving = not last
        return None

    # --- the script command thread ----------------------------------------------------------------

    def _script_commands(self) -> None:
        commands = self.readers["script_command_socket"].messages
        arm, m = self.arm, self.settings.mult_joint
        while commands and self.ended is None:
            raw = commands.popleft()
            cmd, args = raw[0], np.array(raw[1:], np.float64) / m
            if cmd == Command.SET_PAYLOAD or cmd == Command.SET_TARGET_PAYLOAD:
                arm.payload, arm.cog = float(args[0]), (float(args[1]), float(args[2]), float(args[3]))
            elif cmd == Command.SET_TCP_OFFSET:
                self.tool.set_tcp(args[:6])
            elif cmd == Command.SET_GRAVITY:
                arm.gravity = (float(args[0]), float(args[1]), float(args[2]))
            elif cmd == Command.SET_TOOL_VOLTAGE:
                arm.tool_voltage = round(float(args[0]))
            elif cmd == Command.START_FORCE_MODE:
                self._refuse(
                    "force_mode(): this emulated arm has no force control (no force-torque sensor model)"
                )
            elif cmd == Command.START_TOOL_CONTACT:
                self._refuse("tool_contact(): this emulated arm has no contact detection")
            elif cmd == Command.END_TOOL_CONTACT:  # (never in contact: the script's answer then)
                self._send("script_command_socket", TOOL_CONTACT_CANCELED)
            elif cmd == Command.FT_RTDE_INPUT_ENABLE:
                self.messages.append(
                    Message(f"calling ft_rtde_input_enable({bool(raw[1])}, {args[1]:.6g}, ...)")
                )
            # ZERO_FTSENSOR, END_FORCE_MODE and the friction settings change nothing this arm models


def _timed(delta: np.ndarray, v: float, a: float, t: float) -> tuple[float, float]:
    """movej/movel's v and a, or, with a time t > 0 (which a UR honours over v and a), the v and a of
    a trapezoid a third accelerating, a third cruising, a third braking that lasts t."""
    if t <= 0:
        return v, a
    lead = float(np.abs(delta).max()) if delta.size else 0.0
    if lead <= 0:
        return max(v, 1e-3), max(a, 1e-3)
    return 1.5 * lead / t, 4.5 * lead / (t * t)


RUNNERS["external_control"] = ExternalControl
