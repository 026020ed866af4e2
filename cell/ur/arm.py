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
        self._jacobian: np.ndarray | None = None  # (this tick's, once asked for)

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
        self._jacobian = None

    def _pose(self) -> tuple[float, ...]:
        """The TCP pose as a UR gives it: x, y, z (m) and a rotation vector (rad), base frame."""
        return tuple(self.tool.fk(self.q).tolist())

    def jacobian(self) -> np.ndarray:
        """The arm's Jacobian at its joints now (once a tick: the TCP's speed and acceleration)."""
        if self._jacobian is None:
            self._jacobian = self.tool.jacobian(self.q)
        return self._jacobian

    def values(self, name: str) -> tuple:
        """One RTDE output field's values now, flattened (rtde.Source); computed once a tick, once
        for the fields that are the same here (a 500 Hz ur_rtde recipe's ~40 fields, every tick)."""
        key = _SAME.get(name, name)
        got = self._values.get(key)
        if got is None:
            compute = _FIELDS.get(key)
            got = self._values[key] = compute(self) if compute is not None else self._compute(key)
        return got

    def _compute(self, name: str) -> tuple:
        """The fields _FIELDS does not name one by one: the registers, and those with no model here."""
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
        # the fields the emulator has no model of: fixed, plausible values
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


def _configurable(bits: int) -> tuple:
    return ((bits >> 8) & 0xFF,)


def _joint_mode(a: URArm) -> tuple:
    mode = JointMode.RUNNING if a.robot_mode == RobotMode.RUNNING else JointMode.POWER_OFF
    return (int(mode),) * 6


# each RTDE output field the emulator models, by name (URArm.values)
_FIELDS: dict[str, Callable[[URArm], tuple]] = {
    "timestamp": lambda a: (a.timestamp,),
    "actual_q": lambda a: tuple(a.q.tolist()),
    "target_q": lambda a: tuple((a.q if a.reference is None else a.reference[0]).tolist()),
    "actual_qd": lambda a: tuple(a.qd.tolist()),
    "target_qd": lambda a: tuple((a.target_qd if a.reference is None else a.reference[1]).tolist()),
    "actual_qdd": lambda a: tuple(a.qdd.tolist()),
    "actual_TCP_pose": URArm._pose,
    "actual_TCP_speed": lambda a: tuple((a.jacobian() @ a.qd).tolist()),
    # (J q'', as a UR's: no J' q')
    "actual_TCP_acceleration": lambda a: tuple((a.jacobian() @ a.qdd).tolist()),
    "target_moment": lambda a: tuple(a.torques()[0].tolist()),
    "tcp_offset": lambda a: tuple(a.tool.tcp.tolist()),
    "control_step": lambda a: (max(0, round(a.timestamp / CONTROL_STEP_S)),),  # (its 2 ms steps so far)
    "target_gravity": lambda a: a.gravity,
    "tool_output_voltage": lambda a: (a.tool_voltage,),
    "actual_configurable_digital_output_bits": lambda a: _configurable(a.digital_out),
    "actual_configurable_digital_input_bits": lambda a: _configurable(a.digital_in),
    "robot_mode": lambda a: (int(a.robot_mode),),
    "safety_mode": lambda a: (int(a.safety_mode),),
    "joint_mode": _joint_mode,
    "runtime_state": lambda a: (int(a.runtime),),
    "robot_status_bits": lambda a: (a.robot_status_bits,),
    "safety_status_bits": lambda a: (a.safety_status_bits,),
    "speed_scaling": lambda a: (a.speed_fraction if a.can_move else 0.0,),
    "actual_digital_output_bits": lambda a: (a.digital_out,),
    "actual_digital_input_bits": lambda a: (a.digital_in,),
    "actual_execution_time": lambda a: (0.0,),
    "standard_analog_output0": lambda a: (a.analog_out[0],),
    "standard_analog_output1": lambda a: (a.analog_out[1],),
    "payload": lambda a: (a.payload,),
    "payload_cog": lambda a: a.cog,
    # the fields the emulator has no model of: fixed, plausible values
    "actual_main_voltage": lambda a: (48.0,),
    "joint_temperatures": lambda a: (30.0,) * 6,
}
# fields whose values are another's here (computed once a tick for both)
_SAME = {
    "target_TCP_pose": "actual_TCP_pose",
    "target_TCP_speed": "actual_TCP_speed",
    "target_TCP_acceleration": "actual_TCP_acceleration",
    "target_qdd": "actual_qdd",
    "actual_current_as_torque": "target_moment",
    "safety_status": "safety_mode",
    "target_speed_fraction": "speed_scaling",
    "actual_robot_voltage": "actual_main_voltage",
}
