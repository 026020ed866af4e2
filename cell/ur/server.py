"""The UR controller's interfaces of a group's emulated arms, served in the robots process beside their
tick: RTDE (30004) and the dashboard server (29999) on each arm's own address (RobotConfig.ur_host).

RTDE data packages go out from the tick itself (after_tick), on the arm's own 2 ms clock: a client
at 500 Hz gets every status period's state, one at 125 Hz every fourth.  A client that does not
read is not waited for: past WRITE_LIMIT bytes queued its packages are dropped and counted."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass

import numpy as np

from cell.config import CellConfig, RobotConfig
from cell.counters import Counters
from cell.robot.drive import HOLD_UR
from cell.robot.emulator import RobotGroup
from cell.ur.arm import CONTROLLER_VERSION, SafetyMode, URArm
from cell.ur.dashboard import MAX_LINE, WELCOME, Dashboard
from cell.ur.fields import INPUTS, OUTPUTS
from cell.ur.rtde import Session

log = logging.getLogger("cell.ur")
WRITE_LIMIT = 256 * 1024


@dataclass(slots=True)
class URCounters(Counters):
    rtde_clients: int = 0  # connected now (a gauge)
    rtde_connections: int = 0
    rtde_refused: int = 0  # over [ur] max_clients
    rtde_packages_out: int = 0
    rtde_dropped: int = 0  # data packages not sent: the client's queue was full
    rtde_bad: int = 0  # packages refused (each answered with a text message)
    dashboard_clients: int = 0
    dashboard_commands: int = 0
    dashboard_unknown: int = 0
    dashboard_long_lines: int = 0


class _Arm:
    """One arm's UR side: its state, its clients."""

    def __init__(self, group: RobotGroup, row: int, robot: RobotConfig) -> None:
        self.group, self.row, self.robot = group, row, robot
        self.state = URArm(robot.name, group.arm)
        self.rtde: set[RtdeProtocol] = set()
        self.dashboards: set[DashboardProtocol] = set()

    def apply(self) -> None:
        """The UR state onto the drives: an arm that may not move is halted, and let go once it may
        (by its UR state only: an e-stop's hold on it stays)."""
        drives, rows = self.group.drives, np.array([self.row])
        held = bool(drives.holds[self.row] & HOLD_UR)
        if self.state.can_move == held:
            drives.halt(rows, on=not self.state.can_move, by=HOLD_UR)


class URInterfaces:
    def __init__(self, group: RobotGroup, config: CellConfig) -> None:
        self.config = config.ur
        self.group = group
        self.arms = [_Arm(group, row, r) for row, r in enumerate(group.robots)]
        self.counters = URCounters()
        self.servers: list[asyncio.Server] = []

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        for arm in self.arms:
            host = arm.robot.ur_host
            try:
                self.servers.append(
                    await loop.create_server(lambda a=arm: RtdeProtocol(self, a), host, self.config.rtde_port)
                )
                self.servers.append(
                    await loop.create_server(
                        lambda a=arm: DashboardProtocol(self, a), host, self.config.dashboard_port
                    )
                )
            except OSError as exc:
                raise OSError(
                    exc.errno, f"robot {arm.robot.name}: cannot listen on {host} for its UR interfaces: {exc}"
                ) from None

    def close(self) -> None:
        for s in self.servers:
            s.close()
        for arm in self.arms:
            for p in [*arm.rtde, *arm.dashboards]:
                p.transport.abort()

    def after_tick(self, group: RobotGroup, stopping: np.ndarray, resuming: np.ndarray) -> None:
        """The tick's protective stops into the arms' safety modes, then the RTDE packages due."""
        for row in stopping:
            self.arms[row].state.safety_mode = SafetyMode.PROTECTIVE_STOP
        for row in resuming:  # (the cell's own datagram program resumes them by commanding again)
            st = self.arms[row].state
            if st.safety_mode == SafetyMode.PROTECTIVE_STOP:
                st.safety_mode = SafetyMode.NORMAL
        tick = group.tick_no
        # the controller's clock: s since the tick grid's origin (tick k's state is at k periods)
        t = group.state_time - group.origin_ns / 1e9
        b, c = group.backend, self.counters
        for arm in self.arms:
            if not arm.rtde:
                continue
            live = [p for p in arm.rtde if p.session.started]
            if not live:
                continue
            row = arm.row
            arm.state.update(b.q[row], b.qd[row], group.drives.target[row], t)
            for p in live:
                due = p.session.due(tick, arm.state)
                if not due:
                    continue
                if p.transport.get_write_buffer_size() > WRITE_LIMIT:
                    c.rtde_dropped += len(due)
                    continue
                p.transport.write(b"".join(due))
                c.rtde_packages_out += len(due)

    def report(self) -> dict[str, float]:
        c = self.counters
        c.rtde_clients = sum(len(a.rtde) for a in self.arms)
        c.dashboard_clients = sum(len(a.dashboards) for a in self.arms)
        return c.as_dict("ur.")


class RtdeProtocol(asyncio.Protocol):
    def __init__(self, ur: URInterfaces, arm: _Arm) -> None:
        self.ur, self.arm = ur, arm
        self.session = Session(OUTPUTS, INPUTS, arm.state, CONTROLLER_VERSION, arm.robot.status_hz)
        self.transport: asyncio.Transport

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        c = self.ur.counters
        if len(self.arm.rtde) >= self.ur.config.max_clients:
            c.rtde_refused += 1
            transport.close()
            return
        c.rtde_connections += 1
        self.arm.rtde.add(self)

    def data_received(self, data: bytes) -> None:
        s = self.session
        bad = sum(s.counters.bad.values())
        out = s.receive(data)
        self.ur.counters.rtde_bad += sum(s.counters.bad.values()) - bad
        if out:
            self.transport.write(b"".join(out))
        if s.closed:
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self.arm.rtde.discard(self)
        self.session.close()


class DashboardProtocol(asyncio.Protocol):
    def __init__(self, ur: URInterfaces, arm: _Arm) -> None:
        self.ur, self.arm = ur, arm
        robot = arm.robot
        self.dash = Dashboard(arm.state, robot.model, f"2020500{robot.id:05d}", arm.apply)
        self.buf = bytearray()
        self.skipping = False  # inside a line too long to take: its rest is dropped
        self.transport: asyncio.Transport

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        if len(self.arm.dashboards) >= self.ur.config.max_clients:
            transport.close()
            return
        self.arm.dashboards.add(self)
        self.transport.write(WELCOME.encode() + b"\n")

    def data_received(self, data: bytes) -> None:
        c = self.ur.counters
        self.buf += data
        replies: list[str] = []
        while True:
            i = self.buf.find(b"\n")
            if i < 0:
                if len(self.buf) > MAX_LINE:
                    if not self.skipping:
                        c.dashboard_long_lines += 1
                        replies.append(f"could not understand: a line longer than {MAX_LINE} bytes")
                    self.skipping = True
                    self.buf.clear()
                break
            line = bytes(self.buf[:i])
            del self.buf[: i + 1]
            if self.skipping:  # the end of the over-long line
                self.skipping = False
                continue
            c.dashboard_commands += 1
            before = self.dash.unknown
            replies.append(self.dash.handle(line.decode(errors="replace").rstrip("\r")))
            c.dashboard_unknown += self.dash.unknown - before
            if self.dash.closed:
                break
        if replies:
            self.transport.write("".join(r + "\n" for r in replies).encode())
        if self.dash.closed:
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self.arm.dashboards.discard(self)
