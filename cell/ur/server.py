"""The UR controller's interfaces of a group's emulated arms, served in the robots process beside their
tick: RTDE (30004), the dashboard server (29999) and the primary, secondary and real-time client
interfaces (30001-30003: URScript in, messages out) on each arm's own address (RobotConfig.ur_host).

RTDE data packages go out from the tick itself (after_tick), on the arm's own 2 ms clock: a client
at 500 Hz gets every status period's state, one at 125 Hz every fourth; a real-time interface
client (30003) every period's (cell.ur.realtime).  A client that does not read is not waited for:
past WRITE_LIMIT bytes queued its packages are dropped and counted.

A program sent to the client interfaces takes the arm over from the cell's datagram program
(cell.ur.program): the drives take the program's velocities, the data plane's commands are counted
and ignored, and the bus hears it (events/robot/<name>, KIND_PROGRAM / KIND_PROGRAM_END) so the
controller ends its motions of that robot with the reason."""

from __future__ import annotations

import asyncio
import functools
import ipaddress
import logging
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import cast

import numpy as np

from cell.config import CellConfig, RobotConfig
from cell.counters import Counters
from cell.lines import LineReader, TooLong
from cell.robot.backends import MujocoArms, joint_torques
from cell.robot.drive import HOLD_UR
from cell.robot.emulator import RobotGroup
from cell.ur import primary, realtime, robotstate
from cell.ur.arm import CONTROLLER_VERSION, DATAGRAM_PROGRAM, RuntimeState, SafetyMode, URArm
from cell.ur.dashboard import MAX_LINE, WELCOME, Dashboard
from cell.ur.external import ExternalControl
from cell.ur.fields import INPUTS, OUTPUTS
from cell.ur.program import (
    PROTECTIVE_STOP,
    Message,
    ProgramSocket,
    RtdeControl,
    Runner,
    SocketState,
    runner,
)
from cell.ur.programs import Programs
from cell.ur.rtde import Session
from cell.ur.urscript import END_LOOP, EXTERNAL_SOCKETS, Framer, Script, ScriptError, parse
from cell.v1 import robot_pb2

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
    script_clients: int = 0  # on the primary, secondary and real-time interfaces (a gauge)
    states_out: int = 0  # robot state packages (10 Hz) to the primary and secondary clients
    primary_commands: int = 0  # the primary interface's own commands (power on, ...) taken
    states_dropped: int = 0  # not sent: the client's queue was full
    realtime_out: int = 0  # real-time state messages (every tick) to the real-time interface's clients
    realtime_dropped: int = 0  # not sent: the client's queue was full
    scripts_run: int = 0
    scripts_refused: int = 0  # not a program this arm runs, too long, or the arm could not move
    scripts_ended: int = 0
    scripts_failed: int = 0  # ended by a fault (a stop, an unreachable pose, a lost client)


Publish = Callable[[str, object], None]
# after a script ends, no program runs for this long before the datagram program is back (as a URCap
# daemon re-sends its program): a client waiting to see its script gone (ur_rtde's stopScript) sees it
RESTART_S = 0.1
# what a secondary program may not do: move the arm or take time
TIMED_CALLS = frozenset(
    {"movej", "movel", "speedj", "servoj", "stopj", "stopl", "sleep", "sync", "socket_open", END_LOOP}
)
CONNECT_ATTEMPTS, CONNECT_RETRY_S = 5, 0.2  # the external_control program's connect_socket_with_retry
# the primary interface's own commands (not URScript: a UR takes them there as lines of their own),
# as the dashboard's commands they are
PRIMARY_COMMANDS = {
    "power on": "power on",
    "power off": "power off",
    "set robotmode run": "brake release",
    "set unlock protective stop": "unlock protective stop",
    "stop program": "stop",
}


def _offer(transport: asyncio.Transport, data: bytes) -> bool | None:
    """Write to a client that may not read: None if its connection is going, False (not written) if
    it is WRITE_LIMIT bytes behind, True if written.  The arm waits for nobody."""
    if transport.is_closing():
        return None
    if transport.get_write_buffer_size() > WRITE_LIMIT:
        return False
    transport.write(data)
    return True


class _Arm:
    """One arm's UR side: its state, its clients, the program that holds it if not the cell's own."""

    def __init__(self, ur: URInterfaces, group: RobotGroup, row: int, robot: RobotConfig) -> None:
        self.ur, self.group, self.row, self.robot = ur, group, row, robot
        # the program it runs when no script holds it: the cell's datagram program, or (an arm that
        # offers only its UR interfaces, as a real UR) none: it stands until a program is sent
        self.home = DATAGRAM_PROGRAM if group.datagrams else ""
        self.state = URArm(robot.name, group.arm, program=self.home)
        self.state.remote = ur.config.remote_control
        if isinstance(group.backend, MujocoArms):  # (its physics' torques; read between two ticks)
            data, dof = group.backend.data[row], group.dof
            self.state.torques = lambda: joint_torques(data, dof)
        if not group.datagrams:
            self.state.runtime = RuntimeState.STOPPED
            group.drives.script(row, True)
        self.rtde: set[RtdeProtocol] = set()
        self.dashboards: set[DashboardProtocol] = set()
        self.scripts: set[ScriptProtocol] = set()  # clients of 30001-30003 (those of 30001/2 hear messages)
        self.realtime: set[ScriptProtocol] = set()  # those of 30003: told the arm's state every tick
        self.runner: Runner | None = None
        self.t_last = 0.0  # the state time the program last stepped at
        self.restart_at = 0.0  # (monotonic s) when the datagram program comes back; 0: not due
        # an input field whose RTDE client must let go first: a control script that died on an error
        # leaves the arm running nothing while its client is there (as on a UR: runtime STOPPED, so
        # ur_rtde's next call says its script is not running, and it may send it again)
        self.restart_after: str | None = None
        self.ended = ""  # how the last program ended
        self.commands = ur.dashboard_of(self)  # what carries out its primary interface's own commands
        self.said_safety = self.state.safety_mode  # the safety mode its clients were last told
        self.link: asyncio.Task[None] | None = None  # an external_control program's sockets to its client
        self.link_writers: dict[str, asyncio.StreamWriter] = {}
        # the program's own sockets (socket_open): being connected, and connected
        self.opening: dict[ProgramSocket, asyncio.Task[None]] = {}
        self.opened: dict[ProgramSocket, asyncio.StreamWriter] = {}

    def refresh(self) -> None:
        """In the interfaces' per-tick set (URInterfaces.active) while it has an RTDE or a real-time
        client, a program or a restart due; its digital outputs onto the group's as it leaves (a
        fleet of a thousand arms with no client costs the ticks nothing)."""
        if self.rtde or self.realtime or self.runner is not None or self.restart_at:
            self.ur.active.add(self)
        elif self in self.ur.active:
            self.ur.active.discard(self)
            self.group.digital_out[self.row] = self.state.digital_out

    @property
    def datagram_program_runs(self) -> bool:
        st = self.state
        return self.runner is None and st.runtime == RuntimeState.PLAYING and st.program == DATAGRAM_PROGRAM

    def apply(self) -> None:
        """The UR state onto the drives: an arm that may not move is halted, and let go once it may
        (by its UR state only: an e-stop's hold on it stays).  A program ends if the arm stops; the
        data plane's commands reach the drives only while the datagram program runs (a dashboard
        `stop` stops it, `play` starts it again)."""
        self.tell_safety()
        drives, rows = self.group.drives, np.array([self.row])
        held = bool(drives.holds[self.row] & HOLD_UR)
        if self.state.can_move == held:
            drives.halt(rows, on=not self.state.can_move, by=HOLD_UR)
        st = self.state
        if self.runner is not None:
            if not st.can_move:
                self.end(f"the arm stopped: {st.robot_mode.name}, {st.safety_mode.name}")
            elif st.runtime != RuntimeState.PLAYING:
                self.end("stopped from the dashboard")
        elif drives.scripted[self.row] == self.datagram_program_runs:
            runs = self.datagram_program_runs
            what = "started" if runs else "stopped"
            self._datagrams(runs, f"the cell's datagram program was {what} (dashboard)")

    def _datagrams(self, on: bool, text: str) -> None:
        """The data plane's commands reach the drives (on) or are counted and ignored; the bus hears
        which and why (the controller ends its motions of the arm while they do not)."""
        self.group.drives.script(self.row, not on)
        self._event(robot_pb2.RobotEvent.KIND_PROGRAM_END if on else robot_pb2.RobotEvent.KIND_PROGRAM, text)

    # --- programs ----------------------------------------------------------------------------------

    def say(self, m: Message, quiet: bool = False) -> None:
        """To the primary and secondary clients (and the log, unless `quiet`: a refusal is the
        sender's to read, and a flood of them must not flood the log)."""
        t_us = int(time.time() * 1e6)
        if m.key:
            data = primary.key_message(t_us, m.key, m.text)
        elif m.code >= 0:
            self.tell_safety()  # (the safety mode first, as a UR tells it)
            data = primary.error_code(t_us, m.code, 0, primary.ReportLevel.WARNING, m.text)
        elif m.line >= 0:
            data = primary.runtime_exception(t_us, m.line, m.column, m.text)
        else:
            data = primary.text(t_us, m.text)
        for p in self.scripts:
            if p.listens:
                p.transport.write(data)
        if not quiet:
            (log.warning if m.line >= 0 else log.info)("%s: %s", self.robot.name, m.text)

    def tell_safety(self) -> None:
        """The safety mode to the primary and secondary clients, if it changed since they were told
        (a UR tells it only as it changes)."""
        mode = self.state.safety_mode
        if mode == self.said_safety:
            return
        self.said_safety = mode
        t_us = round((self.group.state_time - self.group.origin_ns / 1e9) * 1e6)
        # (and the robot state with it: its robot mode data says the same at once)
        data = primary.safety_mode(t_us, int(mode)) + robotstate.robot_state(self.state, t_us)
        for p in self.scripts:
            if p.listens and not p.transport.is_closing():
                p.transport.write(data)

    def run(self, text: str | ScriptError) -> None:
        """A program from a client interface: refused, or run in place of whatever holds the arm (or
        one of the primary interface's own commands, which UR's client library sends there)."""
        c = self.ur.counters
        if isinstance(text, str) and (command := PRIMARY_COMMANDS.get(text.strip())) is not None:
            self.commands.handle(command)
            c.primary_commands += 1
            return
        try:
            if isinstance(text, ScriptError):
                raise text
            script = parse(text)
        except ScriptError as exc:
            c.scripts_refused += 1
            self.say(Message(exc.said, exc.line, exc.column), quiet=True)
            return
        st = self.state
        if script.secondary:
            self._secondary(script)
            return
        if not st.can_move:
            c.scripts_refused += 1
            reason = f"the arm cannot run a program: {st.robot_mode.name}, {st.safety_mode.name}"
            self.say(Message(reason, 0))
            return
        if self.runner is not None:
            self.end(f"replaced by {script.name}")
        self.restart_at, self.restart_after = 0.0, None
        self.runner = runner(script, st)
        if isinstance(self.runner, ExternalControl):  # (it connects back to its client)
            self.link = self.ur.spawn(self._connect_back(self.runner))
        self.refresh()
        self.t_last = self.group.state_time
        st.program, st.runtime = f"{script.name}.script", RuntimeState.PLAYING
        self.say(Message(script.name, key="PROGRAM_XXX_STARTED"), quiet=True)
        c.scripts_run += 1
        self._datagrams(False, f"URScript program {script.name} holds the arm")

    def _secondary(self, script: Script) -> None:
        """A `sec` program: run at once beside whatever holds the arm (as a UR runs a secondary
        program), or refused if it would move the arm or take time, which a UR's may not."""
        c = self.ur.counters
        timed = [call for call in script.calls if call.name in TIMED_CALLS]
        if timed:
            c.scripts_refused += 1
            call = timed[0]
            self.say(Message(f"{call.name}: a secondary program cannot move the arm or wait", call.line))
            return
        r = runner(script, self.state)
        group = self.group
        r.step(group.q[self.row], group.qd[self.row], 0.0)
        c.scripts_run += 1
        c.scripts_ended += 1
        for m in r.messages:
            self.say(m)
        self.apply()  # (a protective_stop() in it stops the arm and its program)

    def end(self, reason: str) -> None:
        """The program is over: the arm stands, running nothing, until restart() (RESTART_S on)."""
        r, self.runner = self.runner, None
        if r is None:
            return
        self.state.reference = None
        if isinstance(r, ExternalControl):
            self._send_out(r)
        if self.link is not None:  # (its sockets close: the client sees the program gone)
            self.link.cancel()
            self.link = None
        self._sockets(r, ending=True)
        for m in r.messages:
            self.say(m)
        self.say(Message(r.name, key="PROGRAM_XXX_STOPPED"), quiet=True)
        c = self.ur.counters
        c.scripts_ended += 1
        c.scripts_failed += bool(reason)
        self.group.drives.set_target(self.row, 0.0)  # (no program: it stands, the commands still ignored)
        st = self.state
        st.program, st.runtime = self.home, RuntimeState.STOPPED
        self.restart_at = time.monotonic() + RESTART_S
        field = r.cmd_field if isinstance(r, RtdeControl) else None  # (ur_rtde's command register)
        self.restart_after = field if reason and field is not None and st.owner(field) is not None else None
        self.refresh()
        self.ended = f"URScript program {r.name} ended" + (f" ({reason})" if reason else "")
        log.info("%s: %s", self.robot.name, self.ended)

    def restart(self) -> None:
        """The datagram program back after a script (if the arm may move and nothing else came; after
        a control script's error, once its client has let go of it)."""
        if self.restart_after is not None and self.state.owner(self.restart_after) is not None:
            self.restart_at = time.monotonic() + RESTART_S  # (looked at again then)
            return
        self.restart_at, self.restart_after = 0.0, None
        self.refresh()
        st = self.state
        if self.runner is None and st.can_move and st.program == DATAGRAM_PROGRAM:
            st.runtime = RuntimeState.PLAYING
            self._datagrams(True, f"{self.ended}: the cell's datagram program drives the arm again")

    def step(self, q: np.ndarray, qd: np.ndarray) -> None:
        """One tick of the program: its velocities into the drives."""
        r = self.runner
        assert r is not None
        t = self.group.state_time
        dt, self.t_last = max(t - self.t_last, 1e-6), t
        r.live = self.group.live
        v = r.step(q, qd, dt)
        # its target (RTDE's target_q, target_qd): the motion's own reference, or the last target
        # moved on at the velocity the drives are told, as a UR's target integrates its speed;
        # where there is none yet, where the arm stands
        ref, held = r.reference(), self.state.reference
        if ref is None and held is not None:
            ref = (held[0] + v * dt, v.copy())
        elif ref is None and not v.any():
            ref = (q.copy(), np.zeros_like(q))
        self.state.reference = ref
        if isinstance(r, ExternalControl):
            self._send_out(r)
            if r.tail is not None and self.link is not None:  # (its loop is over: it closes them)
                self.link.cancel()
                self.link = None
        if r.sockets or self.opened:
            self._sockets(r)
        for m in r.messages:
            self.say(m)
        r.messages.clear()
        if not self.state.can_move:  # (the program stopped the arm: a protective stop)
            self.apply()
            if self.runner is None:
                return
        if r.ended is not None:
            self.end(r.ended)
        elif (servo := r.servoing()) is None:
            self.group.drives.set_target(self.row, v)
        elif servo.fresh:  # (else the drives' loop runs on with the reference they have)
            servo.fresh = False
            d = self.group.drives
            d.set_servo(self.row, servo.target, servo.ff, servo.t, servo.lookahead, servo.extrapolates)

    async def _connect_back(self, r: ExternalControl) -> None:
        """The external_control program's sockets: opened to its client in the program's order (each
        tried 5 times 0.2 s apart, as its connect_socket_with_retry), then read into the program
        until it ends (cancelled) or the client closes them."""
        s = r.settings
        local = self._local_addr(s.host)
        readers: dict[str, asyncio.StreamReader] = {}
        try:
            for name in EXTERNAL_SOCKETS:
                for _ in range(CONNECT_ATTEMPTS):
                    try:
                        readers[name], self.link_writers[name] = await asyncio.open_connection(
                            s.host, s.ports[name], local_addr=local
                        )
                        break
                    except OSError:
                        await asyncio.sleep(CONNECT_RETRY_S)
                else:
                    reason = (
                        f"external_control: could not connect to {s.host}:{s.ports[name]} ({name}); "
                        f"check that the external control end at {s.host} is running"
                    )
                    r.messages.append(Message(reason, 0))
                    r.ended = reason
                    return
            r.connected = True
            async with asyncio.TaskGroup() as tg:
                for name, reader in readers.items():
                    tg.create_task(self._read_into(r, name, reader))
        finally:
            for w in self.link_writers.values():
                w.close()
            self.link_writers = {}

    @staticmethod
    async def _read_into(r: ExternalControl, name: str, reader: asyncio.StreamReader) -> None:
        while data := await reader.read(65536):
            r.feed(name, data)
        r.lost(name)

    def _local_addr(self, host: str) -> tuple[str, int] | None:
        """Where a program's connection comes from: the arm's own address to a loopback peer (as a
        UR's comes from the UR), else wherever the route says."""
        try:
            return (self.robot.ur_host, 0) if ipaddress.ip_address(host).is_loopback else None
        except ValueError:  # (a host name)
            return None

    def _sockets(self, r: Runner, ending: bool = False) -> None:
        """The program's sockets as it left them this tick: connected (from the arm's own address, as
        the external_control program's), written and closed; all closed as it ends."""
        live = set() if ending else {s for s in r.sockets.values() if s.state != SocketState.CLOSED}
        for s in [s for s in self.opening if s not in live]:
            self.opening.pop(s).cancel()
        for s in [s for s in self.opened if s not in live]:
            self.opened.pop(s).close()
        for s in live:
            if s.state == SocketState.OPENING and s not in self.opening:
                self.opening[s] = self.ur.spawn(self._open(s))
            elif (
                s.outbox
                and (w := self.opened.get(s)) is not None
                and w.transport.get_write_buffer_size() <= WRITE_LIMIT  # (else kept: a UR's would wait)
            ):
                w.write(bytes(s.outbox))
                s.outbox.clear()

    async def _open(self, s: ProgramSocket) -> None:
        """socket_open: connected within its timeout (OPEN) or not (FAILED), as a UR's returns."""
        try:
            async with asyncio.timeout(s.timeout or None):
                _, w = await asyncio.open_connection(s.host, s.port, local_addr=self._local_addr(s.host))
        except (OSError, TimeoutError) as exc:
            s.state = SocketState.FAILED
            log.info("%s: socket_open(%s:%d, %s): %s", self.robot.name, s.host, s.port, s.name, exc)
        else:
            s.state = SocketState.OPEN
            self.opened[s] = w
        finally:
            self.opening.pop(s, None)

    def _send_out(self, r: ExternalControl) -> None:
        """What the program wrote to its sockets this tick (trajectory and tool contact results)."""
        for name, buf in r.outbox.items():
            if buf and (w := self.link_writers.get(name)) is not None and not w.is_closing():
                w.write(bytes(buf))
            buf.clear()

    def _event(self, kind: robot_pb2.RobotEvent.Kind, text: str) -> None:
        log.info("%s: %s", self.robot.name, text)
        if self.ur.publish is not None:
            r = self.robot
            now = time.monotonic_ns()
            ev = robot_pb2.RobotEvent(robot_id=r.id, name=r.name, kind=kind, text=text, t_ns=now)
            self.ur.publish(f"events/robot/{r.name}", ev)


class URInterfaces:
    def __init__(self, group: RobotGroup, config: CellConfig, publish: Publish | None = None) -> None:
        self.config = config.ur
        self.group = group
        self.publish = publish  # onto the bus (events/robot/<name>), if there is one
        self.programs = Programs(config.ur.programs)  # (made on start())
        self.arms = [_Arm(self, group, row, r) for row, r in enumerate(group.robots)]
        self.active: set[_Arm] = set()  # the arms with per-tick work (_Arm.refresh)
        self.counters = URCounters()
        self.servers: list[asyncio.Server] = []
        self.tasks: set[asyncio.Task[None]] = set()  # the programs' connections back to their clients
        # the RTDE packages of the next deadline's state, made after this tick (after_tick) and sent
        # as the period starts (at_deadline), when the state they carry is the arm's: a UR sends its
        # state at the end of the cycle it describes, never before
        self.due: list[tuple[RtdeProtocol, int, bytes, int]] = []  # (client, its session's runs, ...)
        self.realtime_due: list[tuple[ScriptProtocol, bytes]] = []  # (the same for 30003's clients)
        # the arms with clients on 30001/30002: told their robot state at 10 Hz, on the tick grid
        self.stated: set[_Arm] = set()
        self.state_every = max(1, group.robots[0].status_hz // robotstate.STATE_HZ)
        self.next_state_tick = 0
        group.at_deadline = self.at_deadline
        group.busy = self.busy

    def dashboard_of(self, arm: _Arm) -> Dashboard:
        robot = arm.robot
        return Dashboard(arm.state, robot.model, f"2020500{robot.id:05d}", arm.apply, self.programs)

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.programs.ensure()
        for arm in self.arms:
            host = arm.robot.ur_host
            try:
                rtde = functools.partial(RtdeProtocol, self, arm)
                self.servers.append(await loop.create_server(rtde, host, self.config.rtde_port))
                dashboard = functools.partial(DashboardProtocol, self, arm)
                self.servers.append(await loop.create_server(dashboard, host, self.config.dashboard_port))
                for port in (self.config.primary_port, self.config.secondary_port, self.config.realtime_port):
                    script = functools.partial(ScriptProtocol, self, arm, port)
                    self.servers.append(await loop.create_server(script, host, port))
            except OSError as exc:
                raise OSError(
                    exc.errno, f"robot {arm.robot.name}: cannot listen on {host} for its UR interfaces: {exc}"
                ) from None

    def spawn(self, coro: Coroutine[object, object, None]) -> asyncio.Task[None]:
        """A task of these interfaces (cancelled by close())."""
        task = asyncio.get_running_loop().create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    def close(self) -> None:
        for t in list(self.tasks):
            t.cancel()
        for s in self.servers:
            s.close()
        for arm in self.arms:
            clients: list[RtdeProtocol | DashboardProtocol | ScriptProtocol] = [
                *arm.rtde,
                *arm.dashboards,
                *arm.scripts,
            ]
            for p in clients:
                p.transport.abort()

    def after_tick(self, group: RobotGroup, stopping: np.ndarray, resuming: np.ndarray) -> None:
        """The tick's protective stops into the arms' safety modes, then the RTDE packages due."""
        for row in stopping:
            arm = self.arms[row]
            if arm.state.safety_mode != SafetyMode.PROTECTIVE_STOP:
                arm.state.safety_mode = SafetyMode.PROTECTIVE_STOP
                arm.say(PROTECTIVE_STOP, quiet=True)  # (after the mode: its clients hear that first)
        for row in resuming:  # (the cell's own datagram program resumes them by commanding again)
            st = self.arms[row].state
            if st.safety_mode == SafetyMode.PROTECTIVE_STOP:
                st.safety_mode = SafetyMode.NORMAL
        tick = group.tick_no
        # the controller's clock: s since the tick grid's origin (tick k's state is at k periods)
        t = group.state_time - group.origin_ns / 1e9
        for arm in self.active:
            group.digital_out[arm.row] = arm.state.digital_out
            live = [p for p in arm.rtde if p.session.started]
            if not live and not arm.realtime:
                continue
            row = arm.row
            arm.state.update(group.q[row], group.qd[row], group.target[row], t)
            for p in live:
                if due := p.session.due(tick + 1, arm.state):  # (the next tick's state)
                    self.due.append((p, p.session.runs, b"".join(due), len(due)))
            if arm.realtime:
                message = realtime.encode(arm.state.values)
                self.realtime_due.extend((p, message) for p in arm.realtime)

        if self.stated and tick >= self.next_state_tick:
            self.next_state_tick = (tick // self.state_every + 1) * self.state_every
            self._states(group, t)

    def _states(self, group: RobotGroup, t: float) -> None:
        """Each listening client's robot state package (a client that does not read loses them,
        counted, as RTDE's)."""
        c = self.counters
        t_us = round(t * 1e6)
        for arm in self.stated:
            row = arm.row
            if arm.state.timestamp != t:  # (not updated this tick for an RTDE client already)
                arm.state.update(group.q[row], group.qd[row], group.target[row], t)
            arm.tell_safety()
            data = robotstate.robot_state(arm.state, t_us)
            for p in arm.scripts:
                if p.listens and (sent := _offer(p.transport, data)) is not None:
                    c.states_out += sent
                    c.states_dropped += not sent

    def busy(self) -> bool:
        """Whether it needs every tick (an RTDE client, a program running or due back)."""
        return bool(self.active)

    def at_deadline(self) -> None:
        """As a status period starts: the RTDE packages of the state at this deadline go out, then each
        program runs its cycle (reads its inputs, sets the drives for this period), as a UR runs its
        program at the start of every control cycle: what a client wrote during the last period acts
        in this one."""
        self._flush()
        group = self.group
        now = time.monotonic()
        for arm in list(self.active):  # (a program's end or restart changes the set)
            if arm.runner is not None:
                if group.drives.halted[arm.row]:  # (an e-stop on the Responsive Link)
                    arm.end("the arm was halted (emergency stop)")
                else:
                    arm.step(group.q[arm.row], group.qd[arm.row])
            elif arm.restart_at and now >= arm.restart_at:
                arm.restart()

    def _flush(self) -> None:
        """The packages of the state at this deadline, to their clients (a client that does not read
        loses them, counted: the arm waits for nobody)."""
        c = self.counters
        for p, runs, data, n in self.due:
            if p.session.runs != runs:  # (paused or restarted meanwhile)
                continue
            if (sent := _offer(p.transport, data)) is not None:
                c.rtde_packages_out += n * sent
                c.rtde_dropped += n * (not sent)
        self.due.clear()
        for q, message in self.realtime_due:
            if (sent := _offer(q.transport, message)) is not None:
                c.realtime_out += sent
                c.realtime_dropped += not sent
        self.realtime_due.clear()

    def report(self) -> dict[str, float]:
        c = self.counters
        c.rtde_clients = sum(len(a.rtde) for a in self.arms)
        c.dashboard_clients = sum(len(a.dashboards) for a in self.arms)
        c.script_clients = sum(len(a.scripts) for a in self.arms)
        return c.as_dict("ur.")


class RtdeProtocol(asyncio.Protocol):
    def __init__(self, ur: URInterfaces, arm: _Arm) -> None:
        self.ur, self.arm = ur, arm
        self.session = Session(OUTPUTS, INPUTS, arm.state, CONTROLLER_VERSION, arm.robot.status_hz)
        self.transport: asyncio.Transport

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # (a stream server's)
        c = self.ur.counters
        if len(self.arm.rtde) >= self.ur.config.max_clients:
            c.rtde_refused += 1
            transport.close()
            return
        c.rtde_connections += 1
        self.arm.rtde.add(self)
        self.arm.refresh()

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
        self.arm.refresh()
        self.session.close()


class DashboardProtocol(asyncio.Protocol):
    def __init__(self, ur: URInterfaces, arm: _Arm) -> None:
        self.ur, self.arm = ur, arm
        self.dash = ur.dashboard_of(arm)
        self.lines = LineReader(MAX_LINE, b"\n")
        self.transport: asyncio.Transport

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # (a stream server's)
        if len(self.arm.dashboards) >= self.ur.config.max_clients:
            transport.close()
            return
        self.arm.dashboards.add(self)
        self.transport.write(WELCOME.encode() + b"\n")

    def data_received(self, data: bytes) -> None:
        c = self.ur.counters
        replies: list[str] = []
        for line in self.lines.feed(data):
            if isinstance(line, TooLong):
                c.dashboard_long_lines += 1
                replies.append(f"could not understand: a line longer than {MAX_LINE} bytes")
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


class ScriptProtocol(asyncio.Protocol):
    """A client of the primary (30001), secondary (30002) or real-time (30003) interface: URScript
    programs in; on the first two the controller's version, then texts, runtime exceptions and the
    robot state (10 Hz) out; on the third the real-time state message, every tick."""

    def __init__(self, ur: URInterfaces, arm: _Arm, port: int) -> None:
        self.ur, self.arm, self.port = ur, arm, port
        self.listens = port != ur.config.realtime_port
        self.framer = Framer()
        self.transport: asyncio.Transport

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # (a stream server's)
        if sum(p.port == self.port for p in self.arm.scripts) >= self.ur.config.max_clients:
            transport.close()
            return
        self.arm.scripts.add(self)
        if self.port == self.ur.config.realtime_port:
            self.arm.realtime.add(self)
            self.arm.refresh()
        if self.listens:
            major, minor, bugfix, build = CONTROLLER_VERSION
            self.transport.write(primary.version(int(time.time() * 1e6), major, minor, bugfix, build))
            self.ur.stated.add(self.arm)

    def data_received(self, data: bytes) -> None:
        for program in self.framer.feed(data):
            self.arm.run(program)

    def connection_lost(self, exc: Exception | None) -> None:
        self.arm.scripts.discard(self)
        if self in self.arm.realtime:
            self.arm.realtime.discard(self)
            self.arm.refresh()
        if not any(p.listens for p in self.arm.scripts):
            self.ur.stated.discard(self.arm)
