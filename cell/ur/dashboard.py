"""UR's dashboard server (TCP port 29999), sans IO: one "\\n"-ended text command in, one reply line
out, in the controller's own words (what ur_rtde's DashboardClient, UR's client library and URCaps
parse).  The commands change the arm's real state (cell.ur.arm.URArm): powered off or braked, it
does not move.  Programs and installations are loaded from the arm's programs folder, and the logs,
flight reports and support files it is asked for are written there (cell.ur.programs)."""

from __future__ import annotations

from collections.abc import Callable

from cell.ur.arm import POLYSCOPE, RobotMode, RuntimeState, SafetyMode, URArm
from cell.ur.programs import Programs

WELCOME = "Connected: Universal Robots Dashboard Server"
MAX_LINE = 4096  # a longer line is refused (and not buffered), as a UR refuses what it cannot read
_MODEL = {"ur3e": "UR3", "ur5e": "UR5", "ur10e": "UR10", "ur16e": "UR16"}


class Dashboard:
    """One dashboard connection: handle(line) -> the reply line (without its "\\n"); `closed` once
    the client said quit."""

    def __init__(
        self,
        arm: URArm,
        model: str,
        serial: str,
        on_change: Callable[[], None] | None = None,
        programs: Programs | None = None,
    ) -> None:
        self.arm, self.model, self.serial = arm, model, serial
        self.programs = programs or Programs()
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
        if low == "brake release":  # (from POWER_OFF too: a UR powers on first)
            if arm.robot_mode in (RobotMode.POWER_OFF, RobotMode.IDLE, RobotMode.RUNNING):
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
        if (name := _after(cmd, "load installation")) is not None:
            found = self.programs.find(name, ".installation")
            if found is None:
                return f"File not found: {name}"
            arm.installation = found.name
            return f"Loading installation: {found}"
        if word.lower() == "load" and rest:
            name = rest.strip()
            found = self.programs.find(name, ".urp")
            if found is None:
                return f"File not found: {name}"
            arm.program, arm.program_path = found.name, str(found)
            arm.runtime = RuntimeState.STOPPED
            self.on_change()
            return f"Loading program: {found}"
        if low == "get loaded program":
            return (
                f"Loaded program: {arm.program_path or arm.program}" if arm.program else "No program loaded"
            )
        if low == "programstate":
            return f"{arm.runtime.name} {arm.program or '<unnamed>'}"
        if low == "running":
            return f"Program running: {'true' if arm.runtime == RuntimeState.PLAYING else 'false'}"
        if low == "isprogramsaved":
            return f"true {arm.program}"
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
            return arm.operational_mode
        if word.lower() == "addtolog":
            arm.log.append(rest)
            return "Added log message"
        if low == "savelog":
            self.programs.save_log(list(arm.log))
            return "Log saved to disk"
        if (kind := _after(cmd, "generate flight report")) is not None:
            return f"Flight Report generated with id: {self.programs.flight_report(kind, self._state())}"
        if (folder := _after(cmd, "generate support file")) is not None:
            into = self.programs.directory(folder)
            if into is None:
                return "Error: the directory is not in the programs folder"
            return f"Completed successfully: {self.programs.support_file(into, self._state(), list(arm.log))}"
        if (mode := _after(cmd, "set operational mode ")) is not None:
            mode = mode.upper()
            if mode not in ("MANUAL", "AUTOMATIC"):
                return f"Failed to execute: set operational mode {mode.lower()}"
            arm.operational_mode = mode
            return f"Operational mode {mode} is set"
        if low == "clear operational mode":
            arm.operational_mode = "NONE"
            return "No longer controlling the operational mode. Current operational mode: 'NONE'."
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

    def _state(self) -> dict[str, object]:
        """What a flight report or support file says of the arm."""
        a = self.arm
        return {
            "robot_model": _MODEL.get(self.model, self.model.upper()),
            "serial_number": self.serial,
            "polyscope": POLYSCOPE,
            "robot_mode": a.robot_mode.name,
            "safety_mode": a.safety_mode.name,
            "program": a.program,
            "program_state": a.runtime.name,
            "installation": a.installation,
            "q": [float(x) for x in a.q],
        }


def _after(cmd: str, prefix: str) -> str | None:
    """What follows a command's words (any case), stripped; None if cmd is not that command."""
    return cmd[len(prefix) :].strip() if cmd.lower().startswith(prefix) else None
