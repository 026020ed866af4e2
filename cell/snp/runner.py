"""The modular robot on UDP: blocking epoll loops around the sans-IO master and modules.

No asyncio here: a 1 kHz cycle of two query round trips per module has no room for an event
loop's overhead (an asyncio echo costs 50-75 us on this machine, a blocking socket a few).
Each loop sleeps on epoll with a timerfd armed for the next thing due (Python's epoll waits
in whole milliseconds), drains every readable socket, and sends what the state machines
return.  Several modules run as one process, each with its own socket, address and clock:
the protocol stays on the wire.  `loss` drops that share of sent datagrams (a lossy link).
"""

from __future__ import annotations

import contextlib
import random
import select
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cell.sched import Spin
from cell.snp.link import FAILOVER_SENDS, Link, RoutedLink, drain, open_udp
from cell.snp.master import Master
from cell.snp.modular import ModuleState, Stage
from cell.snp.module import JointModule
from cell.snp.native import RUN_HANDED, RUN_RECORDS_FULL, NativeCycles, NativeMaster
from cell.snp.tsp import Oscillator, on_grid
from cell.timer import Alarm, realtime_offset

if TYPE_CHECKING:  # (routed imports runner: its Link)
    from cell.snp.routed import Explored

COARSE_S = 0.05  # epoll's own timeout: the alarm is what wakes a loop on time
# Waking from epoll costs 20-55 us of CPU and as much of latency on this machine kind (a VM), as
# much as handling a datagram: within a cycle the loops poll without sleeping, and they wake a
# little ahead of what is due and wait for it polling (as NAPI busy polling, or a DPDK core).
SPIN_NS = 150_000  # keep polling this long after the last datagram
LEAD_NS = 60_000  # wake this long before a cycle start or deadline


# the precision a master with two-step stamping offers its subscribers (one-step: BeaconSchedule's
# 50 us); measured here: the modules' clocks within 0.85 us of the master's over 60 s
TWO_STEP_PRECISION_NS = 2_000


def chain(n: int, rng: random.Random, transport: str = "snp", module0: int = 101, **extra: Any) -> list[dict]:
    """n modules in a chain on the base plate (module0 + i plugged to the one before), each with its
    own clock error (up to 2 ms and 50 ppm off): Slot arguments (port 0: one to be given)."""
    return [
        {
            "module_id": module0 + i,
            "plugged_to": 0 if i == 0 else module0 + i - 1,
            "port": 0,
            "offset_ns": rng.randint(-2_000_000, 2_000_000),
            "drift_ppm": rng.uniform(-50, 50),
            "transport": transport,
            **extra,
        }
        for i in range(n)
    ]


def _send_timers(master: Master, link: Link) -> None:
    """What the master's timers have due (probes, resends, FDIR), then its beacons, each sent as
    it is made, so that it leaves as it is dated."""
    for data, addr in master.poll():
        link.send(data, addr)
    for data, addr in master.beacons():
        link.send(data, addr)


def _master_link(master: Master, sock: socket.socket, loss: float, routes: Explored | None = None) -> Link:
    """The master's link: here the master's clock is the host's CLOCK_MONOTONIC (its datagrams'
    kernel stamps are taken as its times), so its time packets are stamped with the host's.
    routes: the routed network it found (cell.snp.link.RoutedLink over its two links)."""
    kw: dict[str, Any] = {
        "loss": loss,
        "seed": 1,
        "clock": lambda host_ns: host_ns,
        "departed": master.departed,
    }
    if routes is not None:
        link: Link = RoutedLink(sock, routes.links, routes.own, **kw)
    else:
        link = Link(sock, **kw)
    if link.two_step:  # its beacons' times are the kernel's: that is the precision it offers
        master.beacon_schedule.precision_ns = min(master.beacon_schedule.precision_ns, TWO_STEP_PRECISION_NS)
    return link


def serve_master(
    master: Master,
    sock: socket.socket,
    stop: Callable[[], bool],
    loss: float = 0.0,
    *,
    spin_ns: int = SPIN_NS,
    native: bool = False,
    stop_every_ns: int = int(COARSE_S * 1e9),
    routes: Explored | None = None,
) -> Link:
    """Run the master until stop() is true (asked each pass of its loop; in C at least every
    stop_every_ns, in the management slot: stop may do the caller's own work there); returns its
    link (counters).

    It sleeps (epoll, woken by a datagram or its alarm) until LEAD_NS before the next cycle
    starts or its next timer, then polls without sleeping for as long as the cycle's datagrams
    keep coming (spin_ns after the last one).  native: the cycle's queries and FDIR's watch run
    in C (cell.snp.native.NativeMaster, on the same schedule), the rest here, between its runs.
    routes: the routed network it found, its links to the two routers (cell.snp.routed's
    explore_routers; in C as in Python)."""
    if native:
        return _serve_master_native(master, sock, stop, loss, spin_ns, stop_every_ns, routes)
    link = _master_link(master, sock, loss, routes)
    alarm = Alarm()
    ep = select.epoll()
    ep.register(sock.fileno(), select.EPOLLIN)
    ep.register(alarm.fd, select.EPOLLIN)
    clock = time.monotonic_ns
    mono_of_real = realtime_offset()  # (for the kernel's stamps, if the socket gives them)
    spin_until = 0
    lead = LEAD_NS if spin_ns else 0  # (spin_ns 0: never poll without sleeping)
    due = master.next_due()
    rt = Spin()  # (polls at FIFO within a budget: never into the kernel's RT throttling)
    try:
        while not stop():
            now = clock()
            timeout = 0.0  # poll without sleeping
            if now >= spin_until and (wake := min(due, master.next_cycle_start(now) - lead)) > now:
                alarm.set(wake)
                timeout = COARSE_S
                rt.sleep()
            else:
                rt.poll()
            readable = False
            for fd, _ in ep.poll(timeout):
                if fd == alarm.fd:
                    alarm.clear()
                    spin_until = max(spin_until, clock() + spin_ns + lead)
                else:
                    readable = True
            out: list[tuple[bytes, Any]] = []
            if readable:
                for data, addr, at in drain(sock, mono_of_real):
                    if (got := link.received(data, addr)) is not None:
                        out += master.receive(*got, at)
                spin_until = clock() + spin_ns
            out += master.serve()
            for data, addr in out:
                link.send(data, addr)
            polled = clock() >= due
            if polled:
                _send_timers(master, link)  # (after the replies)
            if polled or out or readable:  # (what it was sent or did may have moved its timers)
                due = master.next_due()
    finally:
        rt.sleep()
        ep.close()
        alarm.close()
    return link


def _serve_master_native(
    master: Master,
    sock: socket.socket,
    stop: Callable[[], bool],
    loss: float,
    spin_ns: int,
    coarse: int,
    routes: Explored | None = None,
) -> Link:
    link = _master_link(master, sock, loss, routes)
    clock = time.monotonic_ns
    lead, mono_of_real = LEAD_NS if spin_ns else 0, realtime_offset()
    fast = NativeMaster(master, sock.fileno(), spin_ns=spin_ns, lead_ns=lead, mono_of_real=mono_of_real)
    fast.st.loss = loss
    master.fdir_here = False
    try:
        while not stop():
            due = master.next_due()
            fast.push()
            if routes is not None:  # (over routers: which router each module was last heard on)
                fast.st.route.take(link)
            got = fast.run(min(due, master.in_management_slot(clock() + coarse)))
            fast.pull(link)
            if routes is not None:
                fast.st.route.give(link)
            out: list[tuple[bytes, Any]] = []
            if got is not None and got[0] == RUN_HANDED:
                _, data, at, addr = got
                if (taken := link.received(data, addr)) is not None:
                    out += master.receive(*taken, at)
            out += master.serve()  # (queries of other shapes, through the handler)
            for data, addr in out:
                link.send(data, addr)
            if clock() >= master.next_due():
                _send_timers(master, link)
    finally:
        master.fdir_here = True
    return link


@dataclass
class Slot:
    """A module on a port of the robot: when it is plugged in and pulled out (s from the start)."""

    module_id: int
    plugged_to: int
    port: int  # UDP port on 127.0.0.1
    plug_s: float = 0.0
    unplug_s: float | None = None
    offset_ns: int = 0  # its oscillator against the master's clock
    drift_ppm: float = 0.0
    transport: str = "snp"
    cd: str = "master"  # a modular arm's module: who computes its [C, D] ("master", "local", "neighbour"),
    adapt: float = 0.0  # its inertial parameters' adaptation gain (0: none),
    believed: float = 1.0  # and the share of its body's true inertia it starts from
    module: JointModule | None = None
    osc: Oscillator | None = None
    sock: socket.socket | None = None
    link: Link | None = None
    master: Any = None  # the master's address, learnt from its first datagram
    inboard: Any = None  # its inboard neighbour's address (a "neighbour" [C, D] passes its force there)
    routes: Any = None  # over a routed network: its links to the two routers (cell.snp.routed)
    route_port: int = 0  # ... and its port on them (its return address)
    clock_errors: list[int] = field(default_factory=list)  # servoed clock - master's, ns
    plugged_at: int = 0
    next_sample: int = 0
    wake: int = 0  # when (host monotonic ns) its module has something due next

    def plug(
        self, t0: int, now: int, loss: float, rmap_timeout_ns: int, rmap_retries: int, plant: Any = None
    ) -> None:
        """A new module, its oscillator (off the host's clock from t0), socket and link; with a plant
        (cell.modular.cycle.Plant), the module it makes for the slot: one of the modular arm, driving
        its joint by VDC."""
        self.osc = Oscillator(self.offset_ns, self.drift_ppm, t0)
        # (port 1: its parent's downstream port)
        self.module = (
            JointModule(self.module_id, self.plugged_to, port=1) if plant is None else plant.module_for(self)
        )
        self.module.use_transport(self.transport, rmap_timeout_ns, rmap_retries)
        self.sock = open_udp("127.0.0.1", self.port, timestamps=True)
        m = self.module
        kw: dict[str, Any] = {
            "loss": loss,
            "seed": self.module_id,
            "clock": self.osc.raw,
            "departed": m.departed,
        }
        if self.routes is not None:
            self.link = RoutedLink(
                self.sock, self.routes, (self.route_port,), failover_after=FAILOVER_SENDS, **kw
            )
        else:
            self.link = Link(self.sock, **kw)
        self.plugged_at = self.wake = now

    def deliver(self, data: bytes, addr: Any, at: int) -> None:
        """A datagram that came in at `at` (host ns) to the module; what it answers, sent back."""
        m, osc, link = self.module, self.osc, self.link
        assert m is not None and osc is not None and link is not None
        got = link.received(data, addr)
        if got is None:
            return
        data, addr = got
        if self.master is None:  # (after that, a datagram may be its outboard neighbour's)
            self.master = addr
        for out in m.receive(data, osc.raw(at)):
            link.send(out, addr)
        self.pass_in()

    def pass_in(self) -> None:
        """What its module has for its inboard neighbour ("neighbour" [C, D]), sent there."""
        out = getattr(self.module, "to_inboard", None)
        if out:
            assert self.link is not None
            for data in out:
                if self.inboard is not None:
                    self.link.send(data, self.inboard)
            out.clear()

    def sample(self, now: int, sample_ns: int, grid: tuple[int, int] | None = None) -> None:
        """Its servoed clock's error against the host's, every sample_ns once it runs (on grid's
        points of host time, if given)."""
        m, osc = self.module, self.osc
        assert m is not None and osc is not None
        if m.state == ModuleState.RUNNING and now >= self.next_sample:
            self.next_sample = _next_sample(now, sample_ns, grid)
            self.clock_errors.append(m.servo.now(osc.raw(now)) - now)


def _inboard(s: Slot, slots: list[Slot]) -> tuple | None:
    """Where a "neighbour" [C, D] passes its force: the module it is plugged to, if that one takes
    it (computes its [C, D] with its neighbour's too); None on the base, or for any other."""
    for o in slots:
        if o.module_id == s.plugged_to and o.cd == "neighbour":  # (over routers: its path)
            return (o.route_port,) if o.routes is not None else ("127.0.0.1", o.port)
    return None


def _next_sample(now: int, sample_ns: int, grid: tuple[int, int] | None) -> int:
    return now + sample_ns if grid is None else on_grid(now + sample_ns, grid)


def _plug_and_pull(
    slots: list[Slot], t0: int, end: int, now: int, plug: Callable[[Slot], None], pull: Callable[[Slot], None]
) -> int:
    """Plug in (plug(s)) and pull out (pull(s)) the slots whose time has come; when the next such
    time is."""
    nxt = end
    for s in slots:
        if s.sock is None and s.module is None:
            at, act = t0 + int(s.plug_s * 1e9), plug
        elif s.sock is not None and s.unplug_s is not None:
            at, act = t0 + int(s.unplug_s * 1e9), pull
        else:
            continue
        if now >= at:
            act(s)
        else:
            nxt = min(nxt, at)
    return nxt


def run_modules(
    slots: list[Slot],
    seconds: float,
    loss: float = 0.0,
    *,
    rmap_timeout_ns: int = 200_000,
    rmap_retries: int = 1,
    sample_ns: int = 10_000_000,
    sample_grid: tuple[int, int] | None = None,
    spin: bool = True,
    native: bool = False,
    plant: Any = None,
    control: Callable[[int], bool] | None = None,
) -> list[Slot]:
    """Run the slots' modules in this thread for `seconds`, plugging and pulling them on time.
    plant: the modular arm they drive by VDC (cell.modular.cycle.Plant; None: the toy joints).
    control(now): called every sample_ns (on sample_grid), where the caller may plug in slots it
    appends to `slots` and pull out ones by setting their unplug_s; True ends the run.
    spin: poll without sleeping while a cycle is in flight (only for a loop with a core of its own:
    a thread that spins starves the others of the GIL).  native: the cycles of the modules with
    transport "snp" run in C (cell.snp.native; the others as before), which needs a C compiler.
    sample_grid: (period, offset) of host time the clock samples are taken on; where the host's
    clock is the master's, its management slot (CycleConfig.management_grid): a sample's trip
    through Python then delays no cycle."""
    if native:
        return _run_native(
            slots, seconds, loss, sample_ns=sample_ns, sample_grid=sample_grid, spin=spin, plant=plant,
            control=control,
        )  # fmt: skip
    alarm = Alarm()
    ep = select.epoll()
    ep.register(alarm.fd, select.EPOLLIN)
    by_fd: dict[int, Slot] = {}
    t0 = time.monotonic_ns()
    mono_of_real = realtime_offset()  # (for the kernel's stamps)
    end = t0 + int(min(seconds, 1e9) * 1e9)  # (seconds inf: until control ends it)

    def plug(s: Slot) -> None:
        s.plug(t0, now, loss, rmap_timeout_ns, rmap_retries, plant)
        s.inboard = _inboard(s, slots)
        assert s.sock is not None
        by_fd[s.sock.fileno()] = s
        ep.register(s.sock.fileno(), select.EPOLLIN)
        live.append(s)

    def pull(s: Slot) -> None:
        assert s.sock is not None
        ep.unregister(s.sock.fileno())
        del by_fd[s.sock.fileno()]
        live.remove(s)
        s.sock.close()
        s.sock = None
        if plant is not None and s.module is not None and s.module.joint >= 0:
            plant.release(s.module.joint)  # (on its brake)

    def wake_of(s: Slot) -> int:
        """When (host monotonic ns) its module has something due next: a cycle start, a
        deadline, a clock sample, or its unplugging."""
        assert s.module is not None and s.osc is not None
        w = s.module.next_wake()
        due = t0 + int(s.unplug_s * 1e9) if s.unplug_s is not None else end
        if w is None:  # not running yet: it waits for datagrams
            return due
        return min(due, s.next_sample, s.osc.true(w))

    def events() -> int:
        return _plug_and_pull(slots, t0, end, now, plug, pull)

    clock = time.monotonic_ns
    lead = LEAD_NS if spin else 0
    live: list[Slot] = []  # the slots plugged in
    now = clock()
    next_event = events()
    next_control = now if control is not None else end
    rt = Spin()  # (polls at FIFO within a budget: never into the kernel's RT throttling)
    try:
        while now < end:
            if now >= next_control:
                assert control is not None  # (without one, next_control is the end)
                if control(now):
                    break
                next_control = _next_sample(now, sample_ns, sample_grid)
                next_event = now  # (it may have plugged or pulled)
            if now >= next_event:
                next_event = events()
            wake, busy = min(next_event, next_control), False
            for s in live:
                wake = min(wake, s.wake)
                cy = s.module.cycle if s.module is not None else None
                busy = busy or (cy is not None and cy.stage != Stage.DONE)
            if not (busy and spin) and wake - now > lead:  # nothing in flight: sleep until (just before) it
                alarm.set(wake - lead)
                rt.sleep()
                ready = ep.poll(COARSE_S)
            else:
                rt.poll()
                ready = ep.poll(0)
            for fd, _ in ready:
                slot = by_fd.get(fd)
                if slot is None:  # the alarm
                    alarm.clear()
                    continue
                assert slot.sock is not None
                for data, addr, at in drain(slot.sock, mono_of_real):
                    slot.deliver(data, addr, at)
                slot.wake = wake_of(slot)
            now = clock()
            for s in live:
                if now >= s.wake:
                    m, osc, link = s.module, s.osc, s.link
                    assert m is not None and osc is not None and link is not None
                    for out in m.poll(osc.raw(now)):
                        link.send(out, s.master)
                    s.pass_in()
                    s.sample(now, sample_ns, sample_grid)
                    s.wake = wake_of(s)
            now = clock()
    finally:
        rt.sleep()
        for s in slots:
            if s.sock is not None:
                with contextlib.suppress(OSError):
                    ep.unregister(s.sock.fileno())
                s.sock.close()
                s.sock = None
        ep.close()
        alarm.close()
    return slots


def _run_native(
    slots: list[Slot],
    seconds: float,
    loss: float,
    *,
    sample_ns: int,
    sample_grid: tuple[int, int] | None,
    spin: bool,
    plant: Any = None,
    control: Callable[[int], bool] | None = None,
) -> list[Slot]:
    """run_modules with the cycle in C (with a plant: VDC's, the plant stepped in C too): one C
    loop waits on every module's socket and runs the running modules' [A, B] and [C, D]; what it
    hands back (configuration, SnP-TSP) goes to the Python JointModule, as do plugging, pulling
    and the clock samples, between its runs.

    Each trip out of C costs what Python does there, and in the management slot a beacon and its
    follow-up make two: only the module that was handed a datagram is pushed to C again (its
    servo or state may have changed), and the C side's records and counters come back when the
    loop returns at `until` (the clock samples: in the management slot), when they fill up, when a
    module is pulled out, and at the end (46 us a trip for six modules had gone into pushing and
    pulling them all and into building the run's arguments anew)."""
    if any(s.transport != "snp" for s in slots):
        raise ValueError("the C cycle runs transport snp only (the RMAP baseline runs in Python)")
    t0 = time.monotonic_ns()
    cycles = NativeCycles(
        spin_ns=SPIN_NS if spin else 0, lead_ns=LEAD_NS if spin else 0, mono_of_real=realtime_offset()
    )
    if plant is not None:
        cycles.drive(plant)
    end = t0 + int(min(seconds, 1e9) * 1e9)  # (seconds inf: until control ends it)
    clock = time.monotonic_ns
    live: list[Slot] = []
    by_fd: dict[int, Slot] = {}

    def push(s: Slot) -> None:
        assert s.sock is not None and s.module is not None
        cycles.push(cycles.state(s.sock.fileno()), s.module, s.master, s.inboard)

    def take(s: Slot) -> None:
        """Its C records and counters into its JointModule and link."""
        assert s.sock is not None and s.module is not None
        cycles.pull(cycles.state(s.sock.fileno()), s.module, s.link)

    def plug(s: Slot) -> None:
        s.plug(t0, now, loss, 0, 0, plant)
        s.inboard = _inboard(s, slots)
        assert s.sock is not None and s.osc is not None
        cycles.attach(s.sock.fileno(), s.osc, loss)
        by_fd[s.sock.fileno()] = s
        live.append(s)
        push(s)

    def pull(s: Slot) -> None:
        assert s.sock is not None
        take(s)
        fd = s.sock.fileno()
        cycles.detach(fd)
        del by_fd[fd]
        live.remove(s)
        s.sock.close()
        s.sock = None
        if plant is not None and s.module is not None and s.module.joint >= 0:
            plant.release(s.module.joint)  # (on its brake)

    def events() -> int:
        return _plug_and_pull(slots, t0, end, now, plug, pull)

    now = clock()
    next_event = events()
    next_control = now if control is not None else end
    try:
        while now < end:
            if now >= next_control:
                assert control is not None  # (without one, next_control is the end)
                if control(now):
                    break
                next_control = _next_sample(now, sample_ns, sample_grid)
                next_event = now  # (it may have plugged or pulled)
            if now >= next_event:
                next_event = events()
            until = min(next_event, next_control)
            for s in live:
                if s.module is not None and s.module.state == ModuleState.RUNNING:
                    until = min(until, s.next_sample)
            routed = [s for s in live if s.routes is not None]
            for s in routed:  # (over routers: the link's state, Python's and C's in turn)
                assert s.sock is not None
                cycles.state(s.sock.fileno()).route.take(s.link)
            fds = [s.sock.fileno() for s in live]  # type: ignore[union-attr]  # (live: plugged, its sock open)
            got = cycles.run(fds, until)
            for s in routed:
                assert s.sock is not None
                cycles.state(s.sock.fileno()).route.give(s.link)
            if got is not None and got[0] == RUN_HANDED:
                _, fd, data, at, addr = got
                s = by_fd[fd]
                s.deliver(data, addr, at)
                push(s)
            elif got is None or got[0] == RUN_RECORDS_FULL:  # (None: at `until`, in the slot)
                for s in live:
                    take(s)
            now = clock()
            for s in live:
                s.sample(now, sample_ns, sample_grid)
    finally:
        for s in live:
            take(s)
        for s in slots:
            if s.sock is not None:
                s.sock.close()
                s.sock = None
    return slots
