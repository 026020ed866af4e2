"""One emulated arm as its UR controller shows it: robot and safety modes, the program state, I/O and
the general purpose registers, and the RTDE output fields computed from the arm's truth once a tick.

The modes are real state: a powered-off or braked arm does not move (its drives are halted), a
protective stop (the watchdog, the data plane's stop, the Responsive Link) shows as one and is
released the way a UR's is (`unlock protective stop` on the dashboard)."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from enum import IntEnum

import numpy as np

from cell.robot.arm import ArmModel
from cell.ur.fields import OUTPUTS
from cell.ur.motion import Tool
from cell.ur.rtde import WIDTH, Type

CONTROLLER_VERSION = (5, 11, 0, 0)  # an e-Series controller on PolyScope 5.11
POLYSCOPE = "5.11.0.108249"
DATAGRAM_PROGRAM = "cell.urp"  # the cell's own program: the data plane's datagrams drive the arm
CONTROL_STEP_S = 0.002  # a UR controller's step (RTDE's control_step counts them)
STANDARD_GRAVITY = 9.82  # m/s^2, as URScript's set_gravity has it


class RobotMode(IntEnum):
    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyMode(IntEnum):
    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class RuntimeState(IntEnum):
    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class JointMode(IntEnum):
    POWER_OFF = 239
    IDLE = 255
    RUNNING = 253


# safety_status_bits: the bit of each safety mode (RTDE guide)
_SAFETY_BIT = {
    SafetyMode.NORMAL: 0, SafetyMode.REDUCED: 1, SafetyMode.PROTECTIVE_STOP: 2, SafetyMode.RECOVERY: 3,
    SafetyMode.SAFEGUARD_STOP: 4, SafetyMode.SYSTEM_EMERGENCY_STOP: 5,
    SafetyMode.ROBOT_EMERGENCY_STOP: 6, SafetyMode.VIOLATION: 8, SafetyMode.FAULT: 9,
}  # fmt: skip
STOPPED_DUE_TO_SAFETY = 1 << 10


class URArm:
    """The UR controller state of one arm (both backends), and its RTDE Source and InputOwner."""

    def __init__(self, name: str, model: ArmModel, program: str = DATAGRAM_PROGRAM) -> None:
        self.name, self.model = name, model
        self.tool = Tool(model)  # the TCP: the flange and a program's set_tcp offset
        # an arm of the cell starts as a UR in remote control, on, brakes released, running the
        # cell's datagram program (the paper's URCap daemon): the data plane drives it from the start
        self.robot_mode = RobotMode.RUNNING
        self.safety_mode = SafetyMode.NORMAL
        self.runtime = RuntimeState.PLAYING
        self.program = program  # the loaded program
        self.remote = True
        self.popup = ""
        self.speed_fraction = 1.0  # the speed slider
        self.int_in = [0] * 48
        self.int_out = [0] * 48
        self.double_in = [0.0] * 48
        self.double_out = [0.0] * 48
        self.bits_in = 0  # input bit registers 0..127 (RTDE's 64..127 are the general purpose ones)
        self.bits_out = 0
        self.digital_out = 0  # standard 0-7, configurable 8-15, tool 16-17 (actual_digital_output_bits)
        self.digital_in = 0
        self.program_path = ""  # the loaded program's file, where the dashboard loaded one
        self.installation = "default.installation"
        self.operational_mode = "NONE"  # (the dashboard's; NONE: not controlled from there)
        self.log: deque[str] = deque(maxlen=1000)  # the dashboard's addToLog lines (saveLog writes them)
        self.analog_out = [0.0, 0.0]
        self.payload, self.cog = 0.0, (0.0, 0.0, 0.0)
        self.gravity = (0.0, 0.0, STANDARD_GRAVITY)  # set_gravity's (default: a robot on the floor)
        self.tool_voltage = 0  # set_tool_voltage's (V)
        self._owners: dict[str, object] = {}  # input field -> the session that holds it
        self.written: dict[str, float] = {}  # input field -> when a package last wrote it (monotonic s)
        dof = model.dof
        self.q = np.zeros(dof)
        self.qd = np.zeros(dof)
        self.qdd = np.zeros(dof)
        self.target_qd = np.zeros(dof)
        self.timestamp = -1.0  # (no state yet)
        # the running program's reference (positions, velocities) where its motion has one (a
        # spline): what a UR reports as target_q and target_qd; else the arm's joints and commands
        self.reference: tuple[np.ndarray, np.ndarray] | None = None
        # its joints' torques now: (the drives', those beyond the arm's own dynamics); a MuJoCo arm's
        # from its physics (set by cell.ur.server), none for an arm without a dynamics model
        self.torques: Callable[[], tuple[np.ndarray, np.ndarray]] = lambda: (np.zeros(dof), np.zeros(dof))
        self._values: dict[str, tuple] = {}  # the fields asked for since the last update, computed

    # --- modes -------------------------------------------------------------------------------

    @property
    def can_move(self) -> bool:
        """Powered, brakes released and no safety stop: only then do its drives take commands."""
        return self.robot_mode == RobotMode.RUNNING and self.safety_mode in (
            SafetyMode.NORMAL,
            SafetyMode.REDUCED,
        )

    @property
    def safety_status_bits(self) -> int:
        bits = 1 << _SAFETY_BIT.get(self.safety_mode, 0)
        return bits | (
            STOPPED_DUE_TO_SAFETY if not self.can_move and self.robot_mode == RobotMode.RUNNING else 0
        )

    @property
    def robot_status_bits(self) -> int:
        on = self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
        return int(on) | (int(self.runtime == RuntimeState.PLAYING) << 1)

    # --- the arm's truth, once a tick -----------------------------------------------------------

    def update(self, q: np.ndarray, qd: np.ndarray, target_qd: np.ndarray, t: float) -> None:
        """The arm's joints at its status time t (s since the tick grid began).  Only what a client's
        recipe asks for is computed from them (values()): no kinematics for a recipe of joints."""
        dt = t - self.timestamp
        if dt > 0 and self.timestamp >= 0:
            self.qdd = (qd - self.qd) / dt
        self.q, self.qd, self.target_qd, self.timestamp = q.copy(), qd.copy(), target_qd.copy(), t
        self._values.clear()

    def _pose(self) -> tuple[float, ...]:
        """The TCP pose as a UR gives it: x, y, z (m) and a rotation vector (rad), base frame."""
        return tuple(self.tool.fk(self.q).tolist())

    def _speed(self) -> tuple[float, ...]:
        """The TCP's velocity, linear (m/s) and angular (rad/s), base frame: the arm's Jacobian."""
        return tuple((self.tool.jacobian(self.q) @ self.qd).tolist())

    def values(self, name: str) -> tuple:
        """One RTDE output field's values now, flattened (rtde.Source)."""
        got = self._values.get(name)
        if got is None:
            got = self._values[name] = self._compute(name)
        return got

    def _compute(self, name: str) -> tuple:
        if name == "timestamp":
            return (self.timestamp,)
        if name == "target_q" and self.reference is not None:
            return tuple(self.reference[0].tolist())
        if name in ("actual_q", "target_q"):
            return tuple(self.q.tolist())
        if name == "target_qd" and self.reference is not None:
            return tuple(self.reference[1].tolist())
        if name in ("actual_qd", "target_qd"):
            return tuple(self.qd.tolist()) if name == "actual_qd" else tuple(self.target_qd.tolist())
        if name in ("actual_qdd", "target_qdd"):
            return tuple(self.qdd.tolist())
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return self._pose()
        if name in ("actual_TCP_speed", "target_TCP_speed"):
            return self._speed()
        if name in ("actual_TCP_acceleration", "target_TCP_acceleration"):  # (J q'', as a UR's: no J' q')
            return tuple((self.tool.jacobian(self.q) @ self.qdd).tolist())
        if name in ("target_moment", "actual_current_as_torque"):
            return tuple(self.torques()[0].tolist())
        if name == "tcp_offset":
            return tuple(self.tool.tcp.tolist())
        if name == "control_step":  # (the controller's 2 ms steps since its start)
            return (max(0, round(self.timestamp / CONTROL_STEP_S)),)
        if name == "target_gravity":
            return self.gravity
        if name == "tool_output_voltage":
            return (self.tool_voltage,)
        if name in ("actual_configurable_digital_output_bits", "actual_configurable_digital_input_bits"):
            bits = self.digital_out if name.endswith("output_bits") else self.digital_in
            return ((bits >> 8) & 0xFF,)
        if name == "robot_mode":
            return (int(self.robot_mode),)
        if name == "safety_mode" or name == "safety_status":
            return (int(self.safety_mode),)
        if name == "joint_mode":
            mode = JointMode.RUNNING if self.robot_mode == RobotMode.RUNNING else JointMode.POWER_OFF
            return (int(mode),) * 6
        if name == "runtime_state":
            return (int(self.runtime),)
        if name == "robot_status_bits":
            return (self.robot_status_bits,)
        if name == "safety_status_bits":
            return (self.safety_status_bits,)
        if name in ("speed_scaling", "target_speed_fraction"):
            return (self.speed_fraction if self.can_move else 0.0,)
        if name == "actual_digital_output_bits":
            return (self.digital_out,)
        if name == "actual_digital_input_bits":
            return (self.digital_in,)
        if name == "actual_execution_time":
            return (0.0,)
        if name.startswith(("output_int_register_", "input_int_register_")):
            regs = self.int_out if name.startswith("output") else self.int_in
            return (regs[int(name.rsplit("_", 1)[1])],)
        if name.startswith(("output_double_register_", "input_double_register_")):
            doubles = self.double_out if name.startswith("output") else self.double_in
            return (doubles[int(name.rsplit("_", 1)[1])],)
        if name.startswith(("output_bit_registers", "input_bit_registers")):
            bits = self.bits_out if name.startswith("output") else self.bits_in
            return ((bits >> (32 if name.endswith("63") else 0)) & 0xFFFFFFFF,)
        if name.startswith(("output_bit_register_", "input_bit_register_")):
            bits = self.bits_out if name.startswith("output") else self.bits_in
            return (bool(bits >> int(name.rsplit("_", 1)[1]) & 1),)
        if name in ("standard_analog_output0", "standard_analog_output1"):
            return (self.analog_out[int(name[-1])],)
        if name == "payload":
            return (self.payload,)
        if name == "payload_cog":
            return self.cog
        # the fields the emulator has no model of: fixed, plausible values
        if name == "actual_main_voltage" or name == "actual_robot_voltage":
            return (48.0,)
        if name == "joint_temperatures":
            return (30.0,) * 6
        zero = False if OUTPUTS[name] == Type.BOOL else 0
        return (zero,) * WIDTH.get(OUTPUTS[name], 1)

    # --- inputs (rtde.InputOwner) ----------------------------------------------------------------

    def claim(self, session: object, names: list[str]) -> list[str]:
        """Give the session the input fields no other session holds; the names it cannot have."""
        taken = [n for n in names if self._owners.get(n, session) is not session]
        if not taken:
            for n in names:
                self._owners[n] = session
        return taken

    def owner(self, name: str) -> object | None:
        return self._owners.get(name)

    def release(self, session: object) -> None:
        for n in [n for n, s in self._owners.items() if s is session]:
            del self._owners[n]

    def write(self, names: list[str], values: tuple) -> None:
        """One input data package: masks first (a value field applies under its mask)."""
        given = dict(zip(names, values, strict=True))
        now = time.monotonic()
        for name in names:
            self.written[name] = now
        for name, v in given.items():
            if name.startswith("input_int_register_"):
                self.int_in[int(name.rsplit("_", 1)[1])] = int(v)
            elif name.startswith("input_double_register_"):
                self.double_in[int(name.rsplit("_", 1)[1])] = float(v)
            elif name == "input_bit_registers0_to_31":
                self.bits_in = (self.bits_in & ~0xFFFFFFFF) | int(v)
            elif name == "input_bit_registers32_to_63":
                self.bits_in = (self.bits_in & ~(0xFFFFFFFF << 32)) | (int(v) << 32)
            elif name.startswith("input_bit_register_"):
                bit = 1 << int(name.rsplit("_", 1)[1])
                self.bits_in = (self.bits_in | bit) if v else (self.bits_in & ~bit)
        if given.get("speed_slider_mask", 0) & 1 and "speed_slider_fraction" in given:
            self.speed_fraction = min(1.0, max(0.0, float(given["speed_slider_fraction"])))
        for mask, value, shift in (
            ("standard_digital_output_mask", "standard_digital_output", 0),
            ("configurable_digital_output_mask", "configurable_digital_output", 8),
            ("tool_digital_output_mask", "tool_digital_output", 16),
        ):
            m = int(given.get(mask, 0)) << shift
            if m and value in given:
                self.digital_out = (self.digital_out & ~m) | ((int(given[value]) << shift) & m)
        m = int(given.get("standard_analog_output_mask", 0))
        for i in (0, 1):
            if m >> i & 1 and f"standard_analog_output_{i}" in given:
                self.analog_out[i] = float(given[f"standard_analog_output_{i}"])
