"""The daemon: a UR controller (a real UR5e, URSim, or an emulated arm offering only its UR interfaces)
as a robot of the cell (RobotConfig backend = "ur").

The paper's URCap daemon (seed 000, Sec. 4) sits between the robot's URScript interface and the
cell's datagrams.  Here it runs beside the cell, in the robots service, and is a RobotGroup of one
robot whose backend is the controller itself:

- it keeps an RTDE session with the controller at the robot's status rate (500 Hz on an e-Series)
  and sends the daemon's program (cell.ur.daemon) to its primary interface;
- each RTDE package is a status period: its actual_q and actual_qd go out at once as the robot's six
  status datagrams, numbered one after the other as an emulated arm numbers the statuses it serves
  (cycles the controller sent no package for are counted, not numbered: a daemon or link stalled
  past the watchdog shows to the data plane as a robot gone quiet);
- the data plane's command datagrams are taken as an emulated arm takes them (Drives: the command
  window, the latest command per joint, the watchdog's protective stop, the Responsive Link's halt),
  and each window's result is one RTDE input package: the window's number and the six velocities,
  which the program speedj's from its next cycle on.

The program runs only while the controller lets it: when the arm may not move (powered off, a safety
stop) or another program holds it, the data plane's commands are counted and ignored and the bus
hears why (events/robot/<name>, KIND_PROGRAM; KIND_PROGRAM_END once the daemon's program runs
again), exactly as for a URScript program on an emulated arm; once no program runs and the arm may
move, the daemon sends its program again ([ur] daemon_restart_s after the last time).
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from cell.config import CellConfig, RobotConfig, URConfig
from cell.counters import Counters
from cell.robot.emulator import Lateness, RobotGroup
from cell.robot.node import register_group_backend
from cell.ur import primary
from cell.ur.arm import RobotMode, RuntimeState, SafetyMode
from cell.ur.client import Client, SetupRefused
from cell.ur.daemon import Registers, script
from cell.v1 import robot_pb2

log = logging.getLogger("cell.ur.daemon")

CONNECT_S = 2.0  # to connect and finish the RTDE handshake
SILENT_S = 1.0  # no RTDE package for this long: the controller is lost
BEAT_PACKAGES = 25  # the heartbeat unchanged over this many packages: the program does not run
RETRY_S = (0.2, 2.0)  # reconnection back-off, first and longest


class DaemonState(Enum):
    CONNECTING = "connecting"  # no RTDE session with the controller
    STARTING = "starting"  # the program was sent; its heartbeat not seen yet
    RUNNING = "running"  # the program runs: the data plane drives the arm
    HELD = "held"  # another program runs (or is paused) on the controller
    STOPPED = "stopped"  # no program runs and the arm may move: the program is sent again
    BLOCKED = "blocked"  # the arm may not move: powered off, braked, a safety stop


def judge(robot_mode: int, safety_mode: int, runtime: int, beating: bool, starting: bool) -> DaemonState:
    """What the controller's state says of the daemon's program (pure: tested on its own)."""
    if robot_mode != RobotMode.RUNNING or safety_mode not in (SafetyMode.NORMAL, SafetyMode.REDUCED):
        return DaemonState.BLOCKED
    if runtime == RuntimeState.PLAYING and beating:
        return DaemonState.RUNNING
    if starting:
        return DaemonState.STARTING
    if runtime in (RuntimeState.STOPPED, RuntimeState.STOPPING):
        return DaemonState.STOPPED
    return DaemonState.HELD


def _mode_name(kind: type[Enum], value: int) -> str:
    try:
        return kind(value).name
    except ValueError:
        return str(value)


Publish = Callable[[str, object], None]


@dataclass(slots=True)
class DaemonCounters(Counters):
    connections: int = 0  # RTDE sessions made
    lost: int = 0  # sessions lost after they started
    programs_sent: int = 0
    packages: int = 0  # RTDE packages served (status periods)
    windows_written: int = 0
    out_of_order: int = 0  # packages whose cycle came before the last's (counted, not served)
    cycles_missed: int = 0  # the controller's cycles it sent no package for
    cycles_missed_max: int = 0  # (a gauge: the longest such gap)
    controller_texts: int = 0
    runtime_exceptions: int = 0


class Daemon(RobotGroup):
    """One robot of backend "ur": its UR controller at RobotConfig.ur_host, through the daemon."""

    def __init__(self, robot: RobotConfig, dataplane: str, host: str, ur: URConfig, publish: Publish | None):
        super().__init__([robot], dataplane, host=host)
        self.ur, self.publish = ur, publish
        self.address = robot.ur_host
        self.registers = Registers(ur.daemon_registers)
        watchdog_cycles = (robot.watchdog_windows + 1) * self.window_ticks * (500 // robot.status_hz)
        lim = self.arm.limits
        self.program = script(self.registers, watchdog_cycles, lim.v_max.tolist(), lim.a_max.tolist())
        self.state = DaemonState.CONNECTING
        self.why = f"connecting to the UR controller at {self.address}"
        self.running: bool | None = None  # what the bus was last told (None: nothing yet)
        self.up = asyncio.Event()  # set while the daemon's program runs
        self.drives.script(0, True)  # (the data plane's commands are ignored until the program runs)
        self.client: Client | None = None
        self._rtde: asyncio.Transport | None = None
        self._primary: asyncio.Transport | None = None
        self._lost: asyncio.Future[str] | None = None
        self._started: asyncio.Future[None] | None = None
        self._pbuf = bytearray()  # the primary interface's bytes not yet framed
        self._on_tick: Callable[[RobotGroup, np.ndarray, np.ndarray], None] | None = None
        self.sent_at = 0.0  # (monotonic s) the program last sent; 0: not yet
        self.awaiting = False  # the program was sent and has not run yet
        self.cut_until = 0.0  # (monotonic s) no session before this (fault injection: silence())
        self.last_sent = False  # the status last sent was its window's last (see commanded())
        self.fresh = np.zeros(self.dof, bool)  # joints answered since
        self.early = False  # the window ending at the next package's boundary has ended already
        self.stops: tuple[list[int], list[int]] = ([], [])  # rows stopped, resumed since the last package
        self._received_ns = 0
        self.beat, self.beat_tick = -1, 0
        self.written = np.full(self.dof, np.nan)  # the velocities last written
        self.window_sent: dict[int, int] = {}  # window number -> when its package ended it (perf ns)
        self.origin_block: list[int] = []
        self.status_us, self.write_us = Lateness(), Lateness()  # (10 us bins)
        self.echo_ms: list[float] = []
        self.stats = DaemonCounters()

    # --- the session -------------------------------------------------------------------------

    async def run(
        self,
        on_tick: Callable[[RobotGroup, np.ndarray, np.ndarray], None] | None = None,
        start_ns: int | None = None,
    ) -> None:
        """Keep a session with the controller for as long as the cell runs, reconnecting with back-off
        (its cycles are the controller's: no start_ns of ours)."""
        self._on_tick = on_tick
        loop = asyncio.get_running_loop()
        loop.add_reader(self.socks[0].fileno(), self.receive)  # (commands as they come: see package())
        wait = RETRY_S[0]
        try:
            while True:
                try:
                    why = await self._session()
                    wait = RETRY_S[0]
                except (OSError, SetupRefused, TimeoutError) as exc:
                    why = str(exc) or type(exc).__name__
                self._close()
                why = f"the UR controller at {self.address} is unreachable: {why}"
                self._become(DaemonState.CONNECTING, why)
                await asyncio.sleep(max(wait, self.cut_until - time.monotonic()))
                wait = min(wait * 2, RETRY_S[1])
        finally:
            loop.remove_reader(self.socks[0].fileno())

    async def _session(self) -> str:
        """One session: connect, hand-shake, then serve packages until the controller is lost (why)."""
        loop = asyncio.get_running_loop()
        self._lost, self._started = loop.create_future(), loop.create_future()
        r = self.registers
        outputs = ["timestamp", "actual_q", "actual_qd", "robot_mode", "safety_mode", "runtime_state",
                   r.taken, r.heartbeat, "actual_digital_output_bits"]  # fmt: skip
        self.client = Client(outputs, [r.window, *r.velocities], float(self.robots[0].status_hz))
        self.beat, self.beat_tick, self.tick_no = -1, 0, -1
        self._pbuf.clear()
        async with asyncio.timeout(CONNECT_S):
            self._primary, _ = await loop.create_connection(
                lambda: _Stream(self._primary_bytes, self._gone), self.address, self.ur.primary_port
            )
            self._rtde, _ = await loop.create_connection(
                lambda: _Stream(self._rtde_bytes, self._gone), self.address, self.ur.rtde_port
            )
            self._rtde.write(self.client.hello())
            either: set[asyncio.Future[Any]] = {self._started, self._lost}
            await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
            if self._lost.done():
                raise OSError(self._lost.result())
        self.stats.connections += 1
        v = self.client.controller or (0, 0, 0, 0)
        log.info("%s: RTDE session with the UR controller at %s (URControl %d.%d.%d.%d)",
                 self.robots[0].name, self.address, *v)  # fmt: skip
        while True:
            seen = self.stats.packages
            try:
                return await asyncio.wait_for(asyncio.shield(self._lost), SILENT_S)
            except TimeoutError:
                if self.stats.packages == seen:
                    return f"no RTDE package for {SILENT_S:g} s"

    def silence(self, robot_id: int, seconds: float) -> bool:
        """Fault injection (`cell chaos`): the link to the controller cut for `seconds`, as if the
        controller went away: no status, no commands, no session until then (the program on the
        controller stops the arm by its own watchdog, and is taken up again once the link is back)."""
        if not super().silence(robot_id, seconds):
            return False
        self.cut_until = time.monotonic() + seconds
        self._gone(f"the link to the controller was cut for {seconds:g} s (fault injection)")
        return True

    def _gone(self, why: str) -> None:
        if self._lost is not None and not self._lost.done():
            self._lost.set_result(why)

    def _close(self) -> None:
        for t in (self._rtde, self._primary):
            if t is not None:
                t.abort()
        self._rtde = self._primary = None
        self.stats.lost += int(self.client is not None and self.client.started)
        self.client = None

    def close(self) -> None:
        self._close()
        super().close()

    # --- bytes in ----------------------------------------------------------------------------

    def _rtde_bytes(self, data: bytes) -> None:
        arrived = time.perf_counter_ns()
        client = self.client
        if client is None:
            return
        try:
            packages = client.feed(data)
        except SetupRefused as exc:
            self._gone(str(exc))
            return
        if client.outbox and self._rtde is not None:
            self._rtde.write(bytes(client.outbox))
            client.outbox.clear()
        if client.started and self._started is not None and not self._started.done():
            self._started.set_result(None)
        for values in packages:
            self.package(values, arrived)

    def _primary_bytes(self, data: bytes) -> None:
        """The controller's messages: its texts and runtime exceptions go to the log (a runtime exception
        in the daemon's program is the reason it stopped)."""
        buf = self._pbuf
        buf += data
        if len(buf) > 1 << 20:  # (a stream that never frames: start over)
            buf.clear()
        for kind, body in primary.split(buf):
            if kind != primary.ROBOT_MESSAGE or len(body) < 10:
                continue  # (the 10 Hz robot state packages of a real controller: RTDE says it all)
            try:
                what, rest = primary.read_robot_message(body)
            except ValueError:
                continue
            name = self.robots[0].name
            if what == primary.RobotMessage.RUNTIME_EXCEPTION and len(rest) >= 8:
                self.stats.runtime_exceptions += 1
                line = int.from_bytes(rest[:4], "big", signed=True)
                log.warning("%s: the controller: line %d: %s", name, line, rest[8:].decode(errors="replace"))
            elif what == primary.RobotMessage.TEXT:
                self.stats.controller_texts += 1
                log.info("%s: the controller says: %s", name, rest.decode(errors="replace"))

    # --- one package: one status period --------------------------------------------------------

    def package(self, values: tuple, arrived_ns: int) -> None:
        """One RTDE package: the status out, the commands in, a window's register write, the program's
        state judged.  (Public for tests and benches that feed packages by hand.)"""
        t, q, qd, robot_mode, safety_mode, runtime, taken, beat, outputs = values
        tick = round(t / self.period)
        if self.tick_no < 0:
            self.tick_no = tick - 1
        periods = tick - self.tick_no
        if periods <= 0:  # (a controller does not resend: a clock reset, say; counted, not served)
            self.stats.out_of_order += 1
            self.tick_no = tick if periods < -1000 else self.tick_no
            return
        self.stats.packages += 1
        if periods > 1:  # cycles the controller sent no package for
            self.stats.cycles_missed += periods - 1
            self.stats.cycles_missed_max = max(self.stats.cycles_missed_max, periods - 1)
        b = self.backend
        b.q[0], b.qd[0] = q, qd
        self.digital_out[0] = outputs
        self._pack()  # (seq + 1: numbered as an emulated arm numbers the statuses it served)
        self._grid(tick)
        self.state_time = (self.origin_ns + tick * round(self.period * 1e9)) / 1e9  # (on our clock)
        self._send(time.monotonic(), time.monotonic)
        self.status_us.add((time.perf_counter_ns() - arrived_ns) / 1e3)
        windows = self.drives.windows
        stopping, resuming = self._windows(tick)
        self.counters.ticks += 1
        self.counters.missed_ticks += periods - 1
        self._program(robot_mode, safety_mode, runtime, beat, tick)
        if self.state in (DaemonState.RUNNING, DaemonState.STARTING):
            target = self.drives.target[0]
            if self.drives.windows != windows or not np.array_equal(target, self.written):
                self._write(target, arrived_ns)
        self._echo(taken, arrived_ns)
        if self._on_tick is not None:
            self._on_tick(self, stopping, resuming)

    # --- command windows ------------------------------------------------------------------------

    def _windows(self, tick: int) -> tuple[np.ndarray, np.ndarray]:
        """The windows that ended with this package (the commands came in as they arrived, see
        commanded()), and the robot's protective stops and resumes since the last package."""
        w = self.window_ticks
        ends = tick // w - self.tick_no // w
        self.tick_no = tick
        if ends and self.early:  # (it ended as its last status was answered)
            ends -= 1
        self.early = False
        for _ in range(ends):
            self._end_window()
        stopping, resuming = np.array(self.stops[0], np.int64), np.array(self.stops[1], np.int64)
        self.stops = ([], [])
        # the status just sent is its window's last: the window ends once every joint has its answer
        self.last_sent = tick % w == w - 1
        self.fresh[:] = False
        return stopping, resuming

    def _end_window(self) -> None:
        stopping, resuming = self.drives.end_window()
        self.stops[0].extend(stopping.tolist())
        self.stops[1].extend(resuming.tolist())
        self.count_stops(stopping, resuming)

    def receive(self, cutoff_ns: int = 0) -> int:
        self._received_ns = time.perf_counter_ns()
        return super().receive(cutoff_ns)

    def commanded(self, joints: np.ndarray) -> None:
        """A window ends the moment every joint has the answer to its last status: what the arm would
        keep of it is in, and written now the program takes it from its next cycle on, the one the
        window ends at (waiting for the next package would start it a cycle late, as it did).  An
        answer that comes after that package lands in the next window, as on an emulated arm."""
        if not self.last_sent:
            return
        self.fresh[joints] = True
        if self.fresh.all():
            self.last_sent, self.early = False, True
            # every joint has a command: the window's result is them, or nothing if the robot is held
            # (written first, the bookkeeping after: end_window() comes to the same target)
            d = self.drives
            if self.state in (DaemonState.RUNNING, DaemonState.STARTING):
                target = np.zeros(self.dof) if d.halted[0] else d.pending[0].copy()
                self._write(target, self._received_ns, d.windows + 1)  # (the number end_window gives it)
            self._end_window()

    def _write(self, target: np.ndarray, arrived_ns: int, number: int | None = None) -> None:
        """The window's velocities and its number (the drives' count of windows) to the registers."""
        if self._rtde is None or self.client is None or not self.client.started:
            return
        number = (self.drives.windows if number is None else number) & 0x7FFFFFFF
        self._rtde.write(self.client.write((number, *target.tolist())))
        self.written = target.copy()
        self.stats.windows_written += 1
        self.write_us.add((time.perf_counter_ns() - arrived_ns) / 1e3)
        self.window_sent[number] = arrived_ns
        if len(self.window_sent) > 64:
            del self.window_sent[next(iter(self.window_sent))]

    def _echo(self, taken: int, arrived_ns: int) -> None:
        """The program took window `taken`: how long after the package that ended it (ms)."""
        sent = self.window_sent.pop(taken, None)
        if sent is not None:
            self.echo_ms.append((arrived_ns - sent) / 1e6)
            del self.echo_ms[:-1024]

    def _grid(self, tick: int) -> None:
        """The controller's cycles on this host's clock: tick 0's monotonic time, from the package of
        least delay over each second (re-estimated: the controller's clock drifts against ours)."""
        period_ns = round(self.period * 1e9)
        self.origin_block.append(time.monotonic_ns() - tick * period_ns)
        if len(self.origin_block) >= round(1 / self.period) or not self.origin_ns:
            self.origin_ns = min(self.origin_block)
            self.origin_block.clear()

    # --- the program ---------------------------------------------------------------------------

    def _program(self, robot_mode: int, safety_mode: int, runtime: int, beat: int, tick: int) -> None:
        if beat != self.beat:
            self.beat, self.beat_tick = beat, tick
        beating = tick - self.beat_tick < BEAT_PACKAGES and self.beat >= 0
        now = time.monotonic()
        # (sent, its heartbeat not seen yet, and not for long: a program that never beats has failed)
        starting = self.awaiting and now - self.sent_at < self.ur.daemon_restart_s
        state = judge(robot_mode, safety_mode, runtime, beating, starting)
        if state == DaemonState.RUNNING:
            self.awaiting = False
        if state == DaemonState.STOPPED and now - self.sent_at >= self.ur.daemon_restart_s:
            self._send_program(now)
            state = DaemonState.STARTING
        if state != self.state:
            self._become(state, self._reason(state, robot_mode, safety_mode))

    def _send_program(self, now: float) -> None:
        if self._primary is None:
            return
        self._primary.write(self.program.encode())
        self.sent_at, self.awaiting = now, True
        self.stats.programs_sent += 1
        self.written[:] = np.nan  # (the program starts from what the registers hold: write them again)

    def _reason(self, state: DaemonState, robot_mode: int, safety_mode: int) -> str:
        at = f"the UR controller at {self.address}"
        if state == DaemonState.BLOCKED:
            modes = f"{_mode_name(RobotMode, robot_mode)}, {_mode_name(SafetyMode, safety_mode)}"
            return f"{at} does not let the arm move: {modes}"
        if state == DaemonState.HELD:
            return f"another program runs on {at}"
        if state == DaemonState.STOPPED:
            return f"no program runs on {at}"
        if state == DaemonState.STARTING:
            return f"the daemon's program was sent to {at}"
        return f"the daemon's program runs on {at}: the cell drives the arm"

    def _become(self, state: DaemonState, why: str) -> None:
        """A new state; the data plane's commands reach the arm only while the program runs, and the bus
        hears when that changes (the controller ends its motions of the arm while they do not)."""
        self.state, self.why = state, why
        running = state == DaemonState.RUNNING
        if running == self.running:
            log.info("%s: %s", self.robots[0].name, why)
            return
        self.running = running
        (self.up.set if running else self.up.clear)()
        self.drives.script(0, not running)
        self.written[:] = np.nan
        (log.info if running else log.warning)("%s: %s", self.robots[0].name, why)
        if self.publish is not None:
            r = self.robots[0]
            RE = robot_pb2.RobotEvent
            kind = RE.KIND_PROGRAM_END if running else RE.KIND_PROGRAM
            ev = RE(robot_id=r.id, name=r.name, kind=kind, text=why, t_ns=time.monotonic_ns())
            self.publish(f"events/robot/{r.name}", ev)

    # --- figures -------------------------------------------------------------------------------

    def report(self) -> dict[str, float]:
        out = self.stats.as_dict("daemon.")
        out["daemon.running"] = float(self.state == DaemonState.RUNNING)  # (summed: daemons running)
        out[f"daemon.{self.robots[0].name}.running"] = out["daemon.running"]
        for name, h in (("status_us", self.status_us), ("write_us", self.write_us)):
            if h.n:
                out[f"daemon.{name}_p50"] = h.percentile(50)
                out[f"daemon.{name}_p99"] = h.percentile(99)
        if self.echo_ms:
            out["daemon.echo_ms_p50"] = float(np.percentile(self.echo_ms, 50))
            out["daemon.echo_ms_p99"] = float(np.percentile(self.echo_ms, 99))
        return out


class _Stream(asyncio.Protocol):
    """A TCP connection whose bytes go to one callback and whose end to another."""

    def __init__(self, on_bytes: Callable[[bytes], None], on_lost: Callable[[str], None]) -> None:
        self.on_bytes, self.on_lost = on_bytes, on_lost

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def data_received(self, data: bytes) -> None:
        self.on_bytes(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.on_lost(f"the controller closed the connection{f': {exc}' if exc else ''}")


def _group(robot: RobotConfig, config: CellConfig, host: str, publish: Publish | None) -> Daemon:
    return Daemon(robot, config.dataplane.address, host, config.ur, publish)


register_group_backend("ur", _group)  # (cell.robot.node builds a "ur" robot's group with it)
