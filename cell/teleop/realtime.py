"""The bilateral experiment in real time: one process per side, talking over the Responsive Link.

    console (this process) --host interface--> local node (1) ==L1 event+data== remote node (2)

Each side is a process pinned to a core of its own at SCHED_FIFO where the
OS allows it, with a Responsive Link node (cell.rlink.link) on one link to
its peer, and a 1 ms loop on a timerfd (cell.timer): take the newest sample
the peer sent, act (cell.teleop.side), send its own sample as one data
packet.  Added delay and jitter go on the data link only, where it reaches
each side's host (cell.teleop.delay); the event link is never delayed.

The console is the operator's panel: it sends START (with the time period 0
begins, so both loops tick together), MODE, ESTOP and STOP as event packets
into the local node's host interface, broadcast to both sides, and hears the
sides' STATE reports.  The local side sends STOP itself when the operator's
script is done.  Each side streams its trace to the console as it goes (for
Rerun) and hands over the whole trace and its timing at the end.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import queue
import random
import socket
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell import aio, sched
from cell.ports import free_port
from cell.rlink.client import KEEPALIVE_S
from cell.rlink.link import LinkPorts, NodeLink, link_counters
from cell.rlink.node import Node
from cell.rlink.packet import EventType, Kind, Packet, PacketError, decode, encode
from cell.rlink.routing import Route, RoutingTable
from cell.teleop import wire
from cell.teleop.delay import DelayLine
from cell.teleop.law import Gains, Mode
from cell.teleop.model import HOME, OBJECTS
from cell.teleop.operator import PUSHES, Operator
from cell.teleop.side import PERIOD_S, Side
from cell.teleop.wire import Role, Sample, State
from cell.timer import PeriodicTimer

ADDRESS = {Role.LOCAL: 1, Role.REMOTE: 2}
BROADCAST = 255
CONSOLE = 0  # the console's source address (it speaks through the local node's host interface)
START_AFTER_S = 0.3  # START names a time this far ahead, so both loops begin period 0 together
CHUNK_S = 0.04  # how often a side streams its new trace rows to the console
RT_PRIORITY = 60
PRIORITY = {EventType.ESTOP: 3, EventType.STOP: 2, EventType.START: 2, EventType.MODE: 2}


@dataclass(frozen=True)
class Setup:
    obj: str = "sponge"
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    mode: Mode = Mode.MODIFIED
    gains: Gains = field(default_factory=Gains)
    pushes: tuple[float, ...] = PUSHES
    coulomb_nm: float = 0.0  # 0: twin drives at the joints; > 0: usual drives with this friction
    estop_at_s: float | None = None  # the console's e-stop, this long after START
    max_s: float = 30.0
    stream: bool = True  # trace rows to the console as the run goes (for Rerun)
    cpus: tuple[int, int] = (0, 1)  # local, remote


def _ports() -> dict[str, tuple[str, int]]:
    names = ("host", "l_ev", "l_da", "r_ev", "r_da")
    return {n: ("127.0.0.1", free_port(socket.SOCK_DGRAM)) for n in names}


def _links(role: Role, ports: dict) -> list[LinkPorts]:
    me, peer = ("l", "r") if role == Role.LOCAL else ("r", "l")
    return [LinkPorts(1, ports[f"{me}_ev"], ports[f"{me}_da"], ports[f"{peer}_ev"], ports[f"{peer}_da"])]


def _table(role: Role) -> RoutingTable:
    me = ADDRESS[role]
    return RoutingTable([Route(links=(1,)), Route(links=(0,), dst=me), Route(links=(0, 1), dst=BROADCAST)])


# --- a side's process -------------------------------------------------------------------------


def side_process(role: Role, setup: Setup, ports: dict, out: Any, quit: Any) -> None:
    problems = sched.place([setup.cpus[role]], RT_PRIORITY, -10)
    sched.settle_heap()
    try:
        result = aio.run(_side(role, setup, ports, out, quit))
        result["placement"] = sched.describe()
        result["placement_problems"] = problems
        out.put(("result", role, result))
    except BaseException as exc:  # the console must hear of it, not wait for a result forever
        out.put(("error", role, f"{type(exc).__name__}: {exc}"))
        raise


async def _side(role: Role, setup: Setup, ports: dict, out: Any, quit: Any) -> dict[str, Any]:
    op = Operator(np.array(HOME), pushes=setup.pushes) if role == Role.LOCAL else None
    obj = OBJECTS[setup.obj] if role == Role.REMOTE else None
    side = Side(role, obj, setup.gains, op, setup.coulomb_nm, capacity=int(setup.max_s / PERIOD_S) + 16)
    peer = ADDRESS[Role.REMOTE if role == Role.LOCAL else Role.LOCAL]
    line: DelayLine[Sample] = DelayLine(setup.delay_ms / 1e3, setup.jitter_ms / 1e3, seed=int(role) + 1)
    started = asyncio.get_running_loop().create_future()
    bad = {"payload": 0}
    handled: list[tuple[str, int, int]] = []  # (event, monotonic ns handled, tick)

    def on_data(batch: list[Packet]) -> None:
        now = time.monotonic()
        for p in batch:
            if p.type != wire.SAMPLE_TYPE:
                continue
            try:
                line.put(now, wire.decode_sample(p.payload))
            except wire.WireError:
                bad["payload"] += 1

    def report() -> None:
        link.send(
            Kind.EVENT, BROADCAST, EventType.STATE, wire.encode_state(role, side.state, side.tick_no), 1
        )

    def on_event(p: Packet) -> None:
        if p.type == EventType.STATE or p.type == EventType.NOP:
            return
        if p.type == EventType.START and not started.done():
            try:
                started.set_result(wire.decode_start(p.payload))
            except wire.WireError:
                bad["payload"] += 1
                return
        before = side.state
        side.event(p.type, p.payload)
        handled.append((EventType(p.type).name, time.monotonic_ns(), side.tick_no))
        if side.state != before:
            report()

    node = Node(ADDRESS[role], _table(role))
    host = ports["host"] if role == Role.LOCAL else None
    link = NodeLink(node, _links(role, ports), on_event, on_data, host=host)
    wake_ns: list[int] = []
    late_ns: list[int] = []  # each wake-up after its deadline
    work_ns: list[int] = []
    missed = 0
    async with asyncio.TaskGroup() as tg:
        runner = tg.create_task(link.run())
        out.put(("ready", role, None))
        start_ns = await started
        timer = PeriodicTimer(start_ns, int(PERIOD_S * 1e9))
        sent_rows = 0
        next_chunk = time.monotonic() + CHUNK_S
        told_done = False
        try:
            while not quit.is_set() and side.tick_no * PERIOD_S < setup.max_s:
                n = await timer.wait()
                t0 = time.monotonic_ns()
                missed += n - 1
                got = line.take(t0 / 1e9)
                s = side.tick(got[-1] if got else None, periods=n, sent_ns=t0)
                link.send(Kind.DATA, peer, wire.SAMPLE_TYPE, wire.encode_sample(s))
                wake_ns.append(t0)
                late_ns.append(t0 - start_ns - (timer.ticks - 1) * timer.period_ns)
                work_ns.append(time.monotonic_ns() - t0)
                if op is not None and op.done and not told_done:
                    told_done = True  # the operator let go: both sides stop
                    link.send(Kind.EVENT, BROADCAST, EventType.STOP, b"", 2)
                if setup.stream and t0 / 1e9 >= next_chunk:
                    next_chunk += CHUNK_S
                    rows = side.trace.data[sent_rows : side.trace.n].copy()
                    sent_rows = side.trace.n
                    with contextlib.suppress(queue.Full):
                        out.put_nowait(("rows", role, rows))
        finally:
            timer.close()
            runner.cancel()
    wake = np.array(wake_ns, dtype=np.int64)
    periods = np.diff(wake) / 1e6 if len(wake) > 1 else np.array([np.nan])
    total = side.tick_no
    return {
        "role": role.name.lower(),
        "trace": side.trace.data[: side.trace.n].copy(),
        "ticks": total,
        "missed_periods": missed,
        "period_ms": periods,
        "wake_late_ms": np.array(late_ns) / 1e6,
        "work_ms": np.array(work_ns) / 1e6,
        "events": handled,
        "log": side.events,
        "stale_periods": side.stale,
        "bad_payloads": bad["payload"],
        "counters": link_counters(link),
        "contact_t": op.contact_t if op is not None else None,
        "lift_t": op.lift_t if op is not None else None,
        "start_ns": start_ns,
    }


# --- the console ------------------------------------------------------------------------------


class Console:
    """The operator's panel: events into the local node's host interface, STATE reports back."""

    def __init__(self, host: tuple[str, int]) -> None:
        self.host = host
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host[0], 0))
        self.sock.setblocking(False)
        self._seq = random.randrange(256)
        self.states: dict[Role, tuple[State, int]] = {}  # the last report of each side, and when (ns)
        self.sent: dict[str, int] = {}  # event name -> monotonic ns it was sent

    def send(self, type: EventType, payload: bytes = b"") -> int:
        p = Packet(Kind.EVENT, BROADCAST, CONSOLE, PRIORITY.get(type, 2), type, self._seq, payload)
        self._seq = (self._seq + 1) & 0xFF
        now = time.monotonic_ns()
        self.sock.sendto(encode(p), self.host)
        if type != EventType.NOP:
            self.sent[EventType(type).name] = now
        return now

    def poll(self) -> None:
        while True:
            try:
                raw = self.sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue
            try:
                p = decode(raw, Kind.EVENT)
                if p.type == EventType.STATE:
                    role, state, _tick = wire.decode_state(p.payload)
                    self.states[role] = (state, time.monotonic_ns())
            except (PacketError, wire.WireError):
                continue

    def close(self) -> None:
        self.sock.close()


class SideDied(RuntimeError):
    """A side's process ended without its result; `survivor` is the other side's result (it holds where
    it was once the dead side's data stop), if it gave one."""

    def __init__(self, role: Role, code: int | None, survivor: dict[str, Any] | None) -> None:
        self.role, self.code, self.survivor = role, code, survivor
        other = "local" if role == Role.REMOTE else "remote"
        said = f"; the {other} side: {survivor['log'][-1][1]}" if survivor and survivor["log"] else ""
        super().__init__(f"the {role.name.lower()} side died (exit code {code}){said}")


def run(
    setup: Setup,
    on_rows: Callable[[Role, np.ndarray], None] | None = None,
    on_ready: Callable[[dict[str, tuple[str, int]], dict[Role, int]], None] | None = None,
) -> dict[str, Any]:
    """Run the experiment; `on_rows` sees each side's trace rows as they come (live drawing), `on_ready`
    the link's addresses and the sides' pids once both are up, before START."""
    ctx = mp.get_context("spawn")
    ports = _ports()
    out, quit = ctx.Queue(), ctx.Event()
    procs = {
        role: ctx.Process(target=side_process, args=(role, setup, ports, out, quit), daemon=True)
        for role in Role
    }
    results: dict[Role, dict[str, Any]] = {}
    console = Console(ports["host"])
    started: list[Any] = []
    try:
        for p in procs.values():
            p.start()
            started.append(p)
        ready: set[Role] = set()
        while len(ready) < 2:
            kind, role, what = _get(out, 60)
            if kind == "error":
                raise RuntimeError(f"the {Role(role).name.lower()} side failed: {what}")
            if kind == "ready":
                ready.add(Role(role))
        if on_ready is not None:
            on_ready(ports, {r: p.pid for r, p in procs.items() if p.pid is not None})  # (all: started)
        if setup.mode != Mode.MODIFIED:
            console.send(EventType.MODE, bytes((setup.mode,)))
        start_ns = time.monotonic_ns() + int(START_AFTER_S * 1e9)
        console.send(EventType.START, wire.encode_start(start_ns))
        estop_ns = start_ns + int(setup.estop_at_s * 1e9) if setup.estop_at_s is not None else None
        give_up = start_ns + int((setup.max_s + 10) * 1e9)
        stopped_ns: int | None = None
        keepalive = 0
        dead: dict[Role, int] = {}  # a side whose process ended, and when that was seen
        while len(results) < 2:
            now = time.monotonic_ns()
            for r, p in procs.items():
                if r not in results and p.exitcode is not None:
                    dead.setdefault(r, now)
                    if now - dead[r] > 1e9:  # (its result, if it put one, had a second to arrive)
                        raise SideDied(r, p.exitcode, _survivor(out, results, quit))
            if now >= keepalive:  # the host interface forgets a console that keeps quiet
                console.send(EventType.NOP)
                keepalive = now + int(KEEPALIVE_S * 1e9)
            if estop_ns is not None and now >= estop_ns:
                console.send(EventType.ESTOP)
                estop_ns = None
                stopped_ns = now
            console.poll()
            done = [
                console.states.get(r, (State.IDLE, 0))[0] in (State.STOPPED, State.ESTOPPED) for r in Role
            ]
            if all(done) and stopped_ns is None:
                stopped_ns = now
            # after a stop, let both sides hold for a moment (the stop itself is in the trace)
            if (stopped_ns is not None and now - stopped_ns > 0.5e9) or now > give_up:
                quit.set()
            try:
                kind, role, what = out.get(timeout=0.01)
            except queue.Empty:
                continue
            if kind == "rows" and on_rows is not None:
                on_rows(Role(role), what)
            elif kind == "result":
                results[Role(role)] = what
            elif kind == "error":
                raise RuntimeError(f"the {Role(role).name.lower()} side failed: {what}")
    finally:
        quit.set()
        console.close()
        for p in started:
            p.join(10)
            if p.is_alive():
                p.kill()
    return {
        "setup": asdict(setup),
        "console_sent_ns": console.sent,
        **{r.name.lower(): results[r] for r in Role},
    }


def _survivor(out: Any, results: dict[Role, dict[str, Any]], quit: Any) -> dict[str, Any] | None:
    """The other side's result, once it is told to finish."""
    quit.set()
    deadline = time.monotonic() + 5
    while not results and time.monotonic() < deadline:
        try:
            kind, role, what = out.get(timeout=0.1)
        except queue.Empty:
            continue
        if kind == "result":
            results[Role(role)] = what
    return next(iter(results.values()), None)


def _get(q: Any, timeout: float) -> tuple[str, int, Any]:
    try:
        return q.get(timeout=timeout)
    except queue.Empty:
        raise RuntimeError("a side did not come up") from None
