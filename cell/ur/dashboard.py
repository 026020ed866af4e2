"""UR's dashboard server (TCP port 29999), sans IO: one "\\n"-ended text command in, one reply line
out, in the controller's own words (what ur_rtde's DashboardClient and URCaps parse).  The commands
change the arm's real state (cell.ur.arm.URArm): powered off or braked, it does not move."""

from __future__ import annotations

from collections.abc import Callable

from cell.ur.arm import POLYSCOPE, RobotMode, RuntimeState, SafetyMode, URArm

WELCOME = "Connected: Universal Robots Dashboard Server"
MAX_LINE = 4096  # a longer line is refused (and not buffered), as a UR refuses what it cannot read
_MODEL = {"ur3e": "UR3", "ur5e": "UR5", "ur10e": "UR10", "ur16e": "UR16"}


class Dashboard:
    """One dashboard connection: handle(line) -> the reply line (without its "\\n"); `closed` once
    the client said quit."""

    def __init__(
        self, arm: URArm, model: str, serial: str, on_change: Callable[[], None] | None = None
    ) -> None:
        self.arm, self.model, self.serial = arm, model, serial
        self.on_change = on_change or (lambda: None)  # the arm's modes changed: apply them to the drives
        self.closed = False
        self.commands = 0
        self.unknown = 0

    def handle(self, line: str) -> str:
        self.commands += 1
        cmd = line.strip()
        low = cmd.lower()
        arm = self.arm
        word, _, rest = cmd.partition(" ")
        if low == "power on":
            if arm.robot_mode in (RobotMode.POWER_OFF, RobotMode.IDLE, RobotMode.RUNNING):
                if arm.robot_mode == RobotMode.POWER_OFF:
                    arm.robot_mode = RobotMode.IDLE  # powered, brakes still on
                    self.on_change()
                return "Powering on"
            return "Failed to execute: power on"
        if low == "power off":
            arm.robot_mode = RobotMode.POWER_OFF
            arm.runtime = RuntimeState.STOPPED
            self.on_change()
            return "Powering off"
        if low == "brake release":
            if arm.robot_mode in (RobotMode.IDLE, RobotMode.RUNNING):
                arm.robot_mode = RobotMode.RUNNING
                self.on_change()
                return "Brake releasing"
            return "Failed to execute: brake release"
        if low == "robotmode":
            return f"Robotmode: {arm.robot_mode.name}"
        if low == "safetymode":
            return f"Safetymode: {arm.safety_mode.name}"
        if low == "safetystatus":
            return f"Safetystatus: {arm.safety_mode.name}"
        if low == "unlock protective stop":
            if arm.safety_mode == SafetyMode.PROTECTIVE_STOP:
                arm.safety_mode = SafetyMode.NORMAL
                self.on_change()
                return "Protective stop releasing"
            return "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"  # noqa: E501
        if low in ("close safety popup", "close popup"):
            arm.popup = ""
            return "closing safety popup" if "safety" in low else "closing popup"
        if word.lower() == "popup":
            arm.popup = rest
            return "showing popup"
        if low == "restart safety":
            arm.safety_mode, arm.robot_mode = SafetyMode.NORMAL, RobotMode.POWER_OFF
            self.on_change()
            return "Restarting safety"
        if low == "play":
            if not arm.program or arm.robot_mode != RobotMode.RUNNING:
                return "Failed to execute: play"
            arm.runtime = RuntimeState.PLAYING
            self.on_change()
            return "Starting program"
        if low == "stop":
            if arm.runtime == RuntimeState.STOPPED:
                return "Failed to execute: stop"
            arm.runtime = RuntimeState.STOPPED
            self.on_change()
            return "Stopped"
        if low == "pause":
            if arm.runtime != RuntimeState.PLAYING:
                return "Failed to execute: pause"
            arm.runtime = RuntimeState.PAUSED
            self.on_change()
            return "Pausing program"
        if word.lower() == "load" and rest:
            arm.program = rest.strip()
            arm.runtime = RuntimeState.STOPPED
            self.on_change()
            return f"Loading program: {arm.program}"
        if low == "get loaded program":
            return f"Loaded program: {arm.program}" if arm.program else "No program loaded"
        if low == "programstate":
            return f"{arm.runtime.name} {arm.program or '<unnamed>'}"
        if low == "running":
            return f"Program running: {'true' if arm.runtime == RuntimeState.PLAYING else 'false'}"
        if low == "isprogramsaved":
            return f"True {arm.program}"
        if low == "is in remote control":
            return "true" if arm.remote else "false"
        if low == "get robot model":
            return _MODEL.get(self.model, self.model.upper())
        if low == "get serial number":
            return self.serial
        if low == "polyscopeversion":
            return f"URSoftware {POLYSCOPE} (Mar 23 2021)"
        if low == "version":
            return POLYSCOPE
        if low == "get operational mode":
            return "NONE"
        if word.lower() == "addtolog":
            return "Added log message"
        if low == "quit":
            self.closed = True
            return "Disconnected"
        if low == "shutdown":
            arm.robot_mode = RobotMode.POWER_OFF
            arm.runtime = RuntimeState.STOPPED
            self.on_change()
            return "Shutting down"
        self.unknown += 1
        return f"could not understand: '{cmd[:200]}'"
