"""A group of emulated robots that tick together: commands in, drives and physics, status out.

One tick per status period, on absolute deadlines (no accumulating sleep
error).  Each tick sends every joint's status (the state at that deadline)
from its robot's own socket, drains the commands that arrived, ends a command
window when one is due (the kept commands execute) and steps the backend to
the next deadline.  A command the kernel stamped after this tick's status went
out belongs to the next window whenever it came (it may answer that very
status, as a data plane in the kernel does within microseconds; on a real arm
such an answer always misses the window that ends as the status leaves).
Nothing here knows about the bus: the robots service publishes what the group
reports, and `cell bench robots` drives groups bare.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import select
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from cell import meter, sched
from cell.config import RobotConfig
from cell.counters import Counters, tally
from cell.robot import datagram, udp
from cell.robot.arm import ArmModel, arm_model
from cell.robot.backends import BACKENDS
from cell.robot.datagram import Kind, Reject
from cell.timer import PeriodicTimer

if TYPE_CHECKING:
    from cell.robot.native import NativeTick

log = logging.getLogger("cell.robots")
_COMMAND = int(Kind.COMMAND)
_NO_ROWS = np.zeros(0, np.int64)  # (no robot stopped or resumed in a tick: the hooks read it, never write)
MAX_READS = 256  # recvmsg calls per socket per tick
# SCHED_FIFO of a robots process's Python while it ticks a group in Python (a UR daemon's): under the
# native loops (the robots' 70, the data plane's 60), over every normal process
PYTHON_TICK_PRIORITY = 50
LATE_READ_NS = 10_000_000  # Python this far behind C's tick while it needs every tick: a late read
CATCH_UP_WINDOWED_S = 0.25  # a tick catching up more than this steps window by window (see tick())


class Lateness:
    """How late ticks started, as a histogram of 10 us bins since start (or clear()): percentiles
    over a whole run at a fixed cost per tick; anything past the last bin counts in it."""

    BIN_US = 10.0
    BINS = 2000  # up to 20 ms

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, np.int64)
        # n, max_us, and the window's count, sum and max since take_window(): an array, so that the
        # tick in C (cell/robot/tick.c) adds to the same histogram Python reads
        self.stats = np.zeros(5)

    @property
    def n(self) -> int:
        return int(self.stats[0])

    @property
    def max_us(self) -> float:
        return float(self.stats[1])

    def add(self, us: float) -> None:
        self.counts[min(int(us / self.BIN_US), self.BINS - 1) if us > 0 else 0] += 1
        self._tally(1, us, us)

    def add_all(self, us: np.ndarray) -> None:
        """Many at once (one per datagram of a batch)."""
        if us.size:
            np.add.at(self.counts, np.clip((us / self.BIN_US).astype(np.int64), 0, self.BINS - 1), 1)
            self._tally(us.size, float(us.sum()), float(us.max()))

    def _tally(self, n: int, total: float, top: float) -> None:
        """n more (summing to total, the largest top) into the run's and the window's stats."""
        st = self.stats
        st[0] += n
        st[1] = max(st[1], top)
        st[2] += n
        st[3] += total
        st[4] = max(st[4], top)

    def take_window(self) -> tuple[int, float, float]:
        """(count, mean, max) of what add_all() added since the last call: a time series beside the
        whole run's histogram."""
        n, total, top = int(self.stats[2]), float(self.stats[3]), float(self.stats[4])
        self.stats[2:] = 0.0
        return n, (total / n if n else 0.0), top

    def clear(self) -> None:
        self.counts[:] = 0
        self.stats[:] = 0.0

    def percentile(self, p: float) -> float:
        """The upper edge of the bin holding the p-th percentile (us)."""
        k = int(np.searchsorted(np.cumsum(self.counts), p / 100 * self.n))
        return (min(k, self.BINS - 1) + 1) * self.BIN_US


@dataclass(slots=True)
class GroupCounters(Counters):
    ticks: int = 0
    status_sent: int = 0
    status_unsent: int = 0  # socket buffer full
    late_sends: int = 0  # left a full status period or more after their deadline
    missed_ticks: int = 0  # status periods that passed with no tick at all (the process was held up)
    ring_overruns: int = 0  # ticks of C's thread Python read too late to read (over its ring's)
    # wakes for every tick (a client streaming, a program) that found Python LATE_READ_NS or more
    # behind C's tick: the host held the process's Python (which runs at the normal policy) that long,
    # and what it serves each tick (RTDE, servoj) was as late
    late_reads: int = 0
    commands: int = 0
    commands_ignored: int = 0  # for robots a URScript program drives (cell.ur): not theirs to take
    rejected: dict[str, int] = tally(keys=tuple(r.name.lower() for r in Reject))
    protective_stops: int = 0
    resumes: int = 0
    lateness: Lateness = field(default_factory=Lateness)  # tick starts after their deadlines
    # each command datagram's time from the status it answers leaving to its arrival (kernel stamps):
    # the whole loop as the robot sees it (the data plane's time and both ways through the network)
    answers: Lateness = field(default_factory=Lateness)

    def as_dict(self, prefix: str = "") -> dict[str, float]:
        out = Counters.as_dict(self, prefix)
        for name, h in (("lateness", self.lateness), ("answer", self.answers)):
            if h.n:
                out[f"{prefix}{name}_p50_us"] = h.percentile(50)
                out[f"{prefix}{name}_p99_us"] = h.percentile(99)
                out[f"{prefix}{name}_max_us"] = h.max_us
        return out


class RobotGroup:
    """Robots of one backend and one schedule, each with its own UDP socket."""

    def __init__(
        self,
        robots: list[RobotConfig],
        dataplane: str,
        host: str = "127.0.0.1",
        arm: ArmModel | None = None,
        datagrams: bool = True,
        tick: str | None = None,
    ) -> None:
        """datagrams=False: robots that neither send status nor take commands (no sockets at all):
        arms that offer only their UR interfaces, as a real UR does (RobotConfig.ur_emulate).
        tick: "native" (C, cell/robot/tick.c) or "python" (the reference model); None: the robots'
        own `tick` setting.  A native tick that cannot run here falls back to Python, `tick_why` says
        why."""
        first = robots[0]
        for r in robots:
            if (r.backend, r.model, r.status_hz, r.command_hz, r.socket, r.tick) != (
                first.backend,
                first.model,
                first.status_hz,
                first.command_hz,
                first.socket,
                first.tick,
            ):
                raise ValueError("a robot group shares backend, model, rates, socket and tick")
        self.robots = robots
        self.n = len(robots)
        self.arm = arm or arm_model(first.model)
        self.dof = dof = self.arm.dof
        self.period = 1.0 / first.status_hz
        self.window_ticks = first.status_hz // first.command_hz
        self.dataplane = udp.address(dataplane)
        q0 = np.array([r.q0 for r in robots], np.float64)
        self.backend = BACKENDS[first.backend](self.arm, q0, first.watchdog_windows)
        self.drives = self.backend.drives
        self.ids = np.array([r.id for r in robots], np.uint16)
        self.datagrams = datagrams
        # one socket a robot (a real arm's own port), or one for the group (first.socket == "shared"):
        # then a robot's row is its id's, not its socket's, and a tick's statuses go out in one GSO run
        self.shared = first.socket == "shared"
        self.socks = []
        try:
            for _ in (robots[:1] if self.shared else robots) if datagrams else ():
                self.socks.append(udp.open_socket(host, timestamps=True))
        except BaseException:
            self.close()
            raise
        self.senders = [udp.Sender(s, datagram.SIZE) for s in self.socks]
        self.row_of_fd = {s.fileno(): i for i, s in enumerate(self.socks)}
        if self.shared:  # robot id -> its row (-1: not of this group)
            self.row_of_id = np.full(0x10000, -1, np.int64)
            self.row_of_id[[r.id for r in robots]] = np.arange(len(robots))
        self.poller = select.epoll()
        for s in self.socks:
            self.poller.register(s.fileno(), select.EPOLLIN)
        self.status = datagram.empty(self.n * dof)
        rows = np.repeat(np.arange(self.n), dof)
        self.status["robot_id"] = self.ids[rows]
        self.status["joint_id"] = np.tile(np.arange(dof), self.n)
        self.status["kind"] = Kind.STATUS
        self._status_bytes = self.status.view(np.uint8).data
        self.seq = np.zeros(self.n * dof, np.uint32)
        self._pack()  # the first status: the start pose
        self.state_time = time.monotonic()
        self.tick_no = -1  # index of the last status period served (period k is due at start + k T)
        self.origin_ns = 0  # CLOCK_MONOTONIC ns period 0 was due at (0: not ticking yet)
        self._counters = GroupCounters()
        # CLOCK_REALTIME each robot's status left in this tick's send (row 0) and the last's (row 1;
        # 0: it did not send): an answer is timed from its own robot's status, not the group's first
        # (a group's later robots send after its first; in the kernel, a data plane answers each
        # robot within microseconds of its own send)
        self.sent_ns = np.zeros((2, self.n), np.int64)
        # fault injection (`cell chaos`): a robot silent until this monotonic time sends no status and
        # takes no command, as with its cable pulled; its watchdog goes on running
        self.silent_until = np.zeros(self.n)
        # commands that came after this tick's status left (see receive()): (rows, joints, velocities)
        self.later: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # called as each status period starts, right after the status went out: what else reports the
        # state of this deadline sends it then (the arms' RTDE packages, cell.ur.server)
        self.at_deadline: Callable[[], None] | None = None
        # whether the tick handed to the hooks is the newest this process knows of (False for the
        # older ticks of the ring a late reader catches up on: run_native)
        self.live = True
        # each robot's digital outputs, as its UR controller has them (cell.ur: set by a program or an
        # RTDE client on an emulated arm, read over RTDE by the daemon); 0 for an arm without
        self.digital_out = np.zeros(self.n, np.uint64)
        # the state the group's readers (truth, RTDE, the Responsive Link node) read after a tick:
        # the live arrays while Python ticks, one tick's copy out of C's ring while C ticks in a thread
        # of its own (run()), so that q, qd, target, velocity and stopped are always of one tick
        self.q, self.qd = self.backend.q, self.backend.qd
        self.target, self.velocity, self.stopped = (
            self.drives.target,
            self.drives.velocity,
            self.drives.stopped,
        )
        # the C thread wakes Python every wake_every-th tick (and on every stop and resume), which then
        # reads each read_every-th tick out of the ring (the truth's grid: several a wake); `busy`
        # (the UR interfaces: RTDE clients, a program) asks to be woken for every tick while it says True
        self.wake_every = 1
        self.read_every = 0  # (0: wake_every's)
        self.busy: Callable[[], bool] | None = None
        self.native: NativeTick | None = None
        self.tick_why = ""  # why this group ticks in Python though its robots asked for C
        if (tick or first.tick) == "native":
            self.tick_why = self._go_native()

    def _go_native(self) -> str:
        """Tick in C from now on; "" if so, else why not."""
        from cell.robot import native  # (ctypes and the build: only for groups that tick in C)

        why = native.supports(self) or native.available()
        if not why:
            self.native = native.NativeTick(self)
        return why

    @property
    def tick_impl(self) -> str:
        """Which tick runs: "native" (C) or "python"."""
        return "native" if self.native is not None else "python"

    @property
    def counters(self) -> GroupCounters:
        if self.native is not None:
            self.native.pull(self._counters)
        return self._counters

    def silence(self, robot_id: int, seconds: float) -> bool:
        """Make one robot stop answering for `seconds`; False if it is not in this group."""
        rows = np.flatnonzero(self.ids == robot_id)
        if rows.size == 0:
            return False
        self.silent_until[rows] = time.monotonic() + seconds
        return True

    def addresses(self) -> list[str]:
        """Each robot's address (the same for all with a shared socket)."""
        return [self.robot_address(row) for row in range(self.n)]

    def robot_address(self, row: int) -> str:
        """Robot `row`'s address, host:port ("" before its socket is open)."""
        if not self.socks:
            return ""
        h, p, *_ = self.socks[0 if self.shared else row].getsockname()
        return f"{h}:{p}"

    def close(self) -> None:
        if hasattr(self, "poller"):
            self.poller.close()
        for s in self.socks:
            s.close()

    # --- one tick --------------------------------------------------------------------------

    def receive(self, cutoff_ns: int = 0) -> int:
        """Take the commands waiting; count and drop what is malformed or foreign.

        Each readable socket is drained (commands sent one by one must all land
        in this window; a flood is capped at MAX_READS a socket a tick, the rest
        waits for the next tick), then one vectorised pass checks everything.
        Commands stamped after cutoff_ns (CLOCK_REALTIME; 0: none) are kept in
        `self.later` for tick() to give the drives once the window has ended.
        """
        size = datagram.SIZE
        chunks: list[bytes] = []
        owners: list[int] = []
        counts: list[int] = []
        stamps: list[int] = []
        rejected = self.counters.rejected
        socks, row_of_fd = self.socks, self.row_of_fd
        for fd, _ in self.poller.poll(0):
            row = row_of_fd[fd]
            sock = socks[row]
            for _ in range(MAX_READS):
                got = udp.recv_batch(sock)
                if got is None:
                    break
                good, bad = udp.whole_datagrams(got[0], got[1], size)
                rejected["length"] += bad
                if good:
                    chunks.append(good)
                    owners.append(row)
                    counts.append(len(good) // size)
                    stamps.append(got[3])
        if not chunks:
            return 0
        at = np.array(stamps, np.int64)  # (kernel receive stamps, CLOCK_REALTIME; 0: none)
        if cutoff_ns:  # (answers to the robot's last status, or to this tick's if after it left)
            rows = np.array(owners)
            now_sent, since = self.sent_ns[0][rows], self.sent_ns[1][rows]
            since = np.where((now_sent > 0) & (at >= now_sent), now_sent, since)
            ok = (at > 0) & (since > 0)
            self.counters.answers.add_all(np.repeat((at - since)[ok] / 1e3, np.array(counts)[ok]))
        recs = datagram.view(b"".join(chunks))
        if self.shared:  # (one socket: each record's robot says whose it is)
            rows = self.row_of_id[recs["robot_id"]]
            bad_robot = rows < 0
            rows[bad_robot] = 0
        else:
            rows = np.repeat(np.array(owners), counts)
            bad_robot = recs["robot_id"] != self.ids[rows]
        late = np.repeat(at > cutoff_ns, counts) if cutoff_ns else None
        bad_kind = recs["kind"] != _COMMAND
        bad_robot &= ~bad_kind
        bad_joint = ~bad_kind & ~bad_robot & (recs["joint_id"] >= self.dof)
        ok = ~(bad_kind | bad_robot | bad_joint)
        n_ok = int(ok.sum())
        if n_ok != recs.size:
            rejected["kind"] += int(bad_kind.sum())
            rejected["robot"] += int(bad_robot.sum())
            rejected["joint"] += int(bad_joint.sum())
            recs, rows = recs[ok], rows[ok]
            late = None if late is None else late[ok]
        if n_ok and self.silent_until.any():  # (a silent robot hears nothing)
            heard = self.silent_until[rows] <= time.monotonic()
            recs, rows, n_ok = recs[heard], rows[heard], int(heard.sum())
            late = None if late is None else late[heard]
        if n_ok:
            joints, velocities = recs["joint_id"].astype(np.int64), datagram.velocities(recs)
            if late is not None and late.any():
                self.later = (rows[late], joints[late], velocities[late])
                now = ~late
                rows, joints, velocities = rows[now], joints[now], velocities[now]
            self.drives.command(rows, joints, velocities)
            self.counters.commands += n_ok
            self.commanded(joints)
        return n_ok

    def commanded(self, joints: np.ndarray) -> None:
        """The joints just commanded (in this window): a hook (cell.ur.remote ends a window on it)."""

    def tick(
        self, deadline: float, periods: int = 1, clock: Callable[[], float] = time.monotonic
    ) -> tuple[np.ndarray, np.ndarray]:
        """Serve the status period due at `deadline`; return (rows that stopped, rows that resumed).

        The status goes out first: it was packed at the end of the last tick, so it is the
        state at `deadline`, sent the moment the period starts.  Then the commands that came
        in are taken, a window ends if one is due, and the robots move on to the next
        deadline, `periods` periods later if ticks were missed (they move for all of it).
        """
        cutoff_ns = time.time_ns()  # (the kernel stamps datagrams in CLOCK_REALTIME)
        if self.native is not None:
            self.native.send(deadline)
            if self.at_deadline is not None:
                self.at_deadline()
            stopping, resuming = self.native.after(cutoff_ns, periods)
            self.state_time = deadline + self.period
            return stopping, resuming
        self._send(deadline, clock)
        if self.at_deadline is not None:
            self.at_deadline()
        stopping, resuming, left = self.take(cutoff_ns, periods)
        self.drives.servo(self.backend.q, self.period * periods)
        self.backend.step(self.period * left)
        # the instant q, qd now describe: one period past the latest deadline (the backend stepped from
        # the last state, one period past the last tick's deadline, over every period missed since)
        self.state_time = deadline + self.period
        self._pack()
        self.counters.ticks += 1
        self.counters.missed_ticks += periods - 1
        return stopping, resuming

    def take(self, cutoff_ns: int, periods: int) -> tuple[np.ndarray, np.ndarray, int]:
        """After a status went out: the commands that came in, and the command windows that ended
        over the `periods` status periods since the last one; (rows that stopped, rows that resumed,
        the periods the backend has yet to step)."""
        self.receive(cutoff_ns)
        stopping = resuming = np.empty(0, np.int64)
        last, self.tick_no = self.tick_no, self.tick_no + periods
        # windows end at periods W, 2W, ... (W status periods a window); one may have ended since last
        w = self.window_ticks
        ends = self.tick_no // w - max(last, 0) // w
        if ends:
            stopping, resuming = self.drives.end_window()
        # a long catch-up (the process was held up: SIGSTOP, a hung host) goes window by window: each
        # window after the first ended with no command, as the robot would have seen it, so the
        # watchdog stops it within its windows rather than letting it run seconds on its last
        # command (it ran 0.64 rad past where it was in `cell chaos`, hang:robots).  A short one is
        # the emulating process's hiccup on a busy machine, not the robot's: it runs on as before
        left = periods
        windowed = periods * self.period > CATCH_UP_WINDOWED_S
        for _ in range(ends - 1 if windowed else 0):
            chunk = min(w, left - 1)
            if chunk:
                self.backend.step(self.period * chunk)
            left -= chunk
            more, _ = self.drives.end_window()
            stopping = np.union1d(stopping, more)
        if self.later is not None:  # the answers to this tick's status: the next window's
            self.drives.command(*self.later)
            self.later = None
        self.count_stops(stopping, resuming)
        return stopping, resuming, left

    def count_stops(self, stopping: np.ndarray, resuming: np.ndarray) -> None:
        """The counters of windows that ended: protective stops and resumes, the commands ignored."""
        c = self.counters
        c.protective_stops += stopping.size
        c.resumes += resuming.size
        c.commands_ignored = self.drives.ignored

    def _pack(self) -> None:
        """The next status of every joint, ready to go at the next deadline."""
        self.seq += 1
        st = self.status
        st["seq"] = self.seq
        st["velocity"] = np.rint(self.backend.qd.ravel() * datagram.SCALE)
        st["position"] = np.rint(self.backend.q.ravel() * datagram.SCALE)

    def _send(self, deadline: float, clock: Callable[[], float]) -> None:
        chunk = self.dof * datagram.SIZE
        buf, addr = self._status_bytes, self.dataplane
        late_after = deadline + self.period
        silent = self.silent_until > clock() if self.silent_until.any() else None
        self.sent_ns[1] = self.sent_ns[0]
        self.sent_ns[0] = 0
        if self.shared and self.socks:
            if silent is not None:  # (rare: `cell chaos` pulled a cable) the others' statuses only
                buf = self.status[np.repeat(~silent, self.dof)].view(np.uint8).data
            self.sent_ns[0] = time.time_ns()
            sent = udp.send_segments(self.socks[0], buf, datagram.SIZE, addr)
            self._count_sent(sent, len(buf) // datagram.SIZE, clock() >= late_after)
            return
        for r, sender in enumerate(self.senders):
            if silent is not None and silent[r]:
                continue
            self.sent_ns[0, r] = time.time_ns()
            sent = sender.send(buf[r * chunk : (r + 1) * chunk], addr)
            self._count_sent(sent, self.dof, clock() >= late_after)

    def _count_sent(self, sent: int, of: int, late: bool) -> None:
        """Status datagrams sent (of `of`; the rest a full socket buffer kept), late or not."""
        c = self.counters
        c.status_sent += sent
        c.status_unsent += of - sent
        if late:
            c.late_sends += sent

    # --- the schedule ----------------------------------------------------------------------

    async def run(
        self,
        on_tick: Callable[[RobotGroup, np.ndarray, np.ndarray], None] | None = None,
        start_ns: int | None = None,
    ) -> None:
        """Tick forever on absolute deadlines from start_ns (CLOCK_MONOTONIC; None: a period from now);
        on_tick(group, stopped rows, resumed rows) after each.  A native group ticks in C's own thread
        (run_native); this one calls on_tick as it reads the ticks."""
        if self.native is not None:
            await self.run_native(on_tick, start_ns)
            return
        period_ns = round(self.period * 1e9)
        timer = PeriodicTimer(time.monotonic_ns() + period_ns if start_ns is None else start_ns, period_ns)
        self.origin_ns = timer.start_ns  # period 0's deadline (CLOCK_MONOTONIC): the tick grid
        lateness = self.counters.lateness
        try:
            while True:
                periods = await timer.wait()
                deadline = (timer.start_ns + (timer.ticks - 1) * period_ns) / 1e9
                # (late against the deadline waited for, as tick.c: a wake past the next one too shows
                # as late as it was)
                waited = deadline - (periods - 1) * period_ns / 1e9
                lateness.add((time.monotonic() - waited) * 1e6)
                stopping, resuming = self.tick(deadline, periods)
                if on_tick is not None:
                    on_tick(self, stopping, resuming)
        finally:
            timer.close()

    async def run_native(
        self,
        on_tick: Callable[[RobotGroup, np.ndarray, np.ndarray], None] | None = None,
        start_ns: int | None = None,
    ) -> None:
        """The tick in C's own thread (cell/robot/tick.c), the only thread of the process left at its
        real-time priority (sched.hand_over); this one reads the ticks out of its ring when woken
        and runs the hooks (at_deadline, on_tick) on each tick it reads, at the normal policy."""
        assert self.native is not None
        native = self.native
        period_ns = round(self.period * 1e9)
        self.origin_ns = time.monotonic_ns() + period_ns if start_ns is None else start_ns
        live = (self.q, self.qd, self.target, self.velocity, self.stopped)
        self.q, self.qd = self.q.copy(), self.qd.copy()
        self.target, self.velocity, self.stopped = (
            self.target.copy(),
            self.velocity.copy(),
            self.stopped.copy(),
        )
        loop = asyncio.get_running_loop()
        fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        woken = asyncio.Event()
        loop.add_reader(fd, woken.set)
        try:
            tid = native.start(self.origin_ns, fd, self._wake_every(), sched.LOOP_PRIORITY)
            for problem in sched.hand_over(tid):
                log.warning("%s", problem)
            if tid in sched.RT_THREADS:
                meter.watch_thread(tid)
            seen, late = 0, max(1, LATE_READ_NS // period_ns)
            while True:
                await woken.wait()
                woken.clear()
                with contextlib.suppress(BlockingIOError):
                    os.eventfd_read(fd)
                if native.state.wake_every == 1 and seen and int(native.state.ring_head) - seen >= late:
                    self._counters.late_reads += 1
                seen = self._read_ticks(seen, on_tick)
                native.state.wake_every = self._wake_every()
        finally:
            loop.remove_reader(fd)
            native.stop()
            os.close(fd)
            self.q, self.qd, self.target, self.velocity, self.stopped = live

    def _wake_every(self) -> int:
        return 1 if self.busy is not None and self.busy() else max(1, self.wake_every)

    def _read_every(self) -> int:
        if self.busy is not None and self.busy():
            return 1
        return max(1, min(self.read_every or self.wake_every, self.wake_every))

    def _read_ticks(self, seen: int, on_tick: Callable | None) -> int:
        """The ticks C wrote since `seen` (up to the ring's last RING), each one that matters read into
        the group's state and handed to the hooks: with every tick asked for, each one; else those a
        robot stopped or resumed in, those on the read grid, and the last.  The new `seen`."""
        native = self.native
        assert native is not None
        head, cap = int(native.state.ring_head), len(native.ring_tick)
        if head - seen > cap:
            self._counters.ring_overruns += head - seen - cap
            seen = head - cap
        every = self._read_every()  # (what is needed now: a client that just came gets every tick)
        period_ns = round(self.period * 1e9)
        slots = np.arange(seen, head) % cap
        if every > 1 and slots.size > 1:  # (picked in one go: this runs at the truth's rate)
            pick = (native.ring_tick[slots] % every == 0) | native.ring_flags[slots].any(axis=1)
            pick[-1] = True
            slots = slots[pick]
        last = int(slots[-1]) if slots.size else -1
        for slot in slots.tolist():
            # (the ticks before the newest are ones this reader is late for: a hook that measures a
            # client's silence in ticks does not count them, as the client's data waits unread too)
            self.live = slot == last
            tick, flags = int(native.ring_tick[slot]), native.ring_flags[slot]
            self.tick_no = tick
            self.state_time = (self.origin_ns + tick * period_ns) / 1e9 + self.period
            self.q[:], self.qd[:] = native.ring_q[slot], native.ring_qd[slot]
            self.target[:], self.velocity[:] = native.ring_target[slot], native.ring_velocity[slot]
            self.stopped[:] = native.ring_stopped[slot]
            if self.at_deadline is not None:
                self.at_deadline()
            if on_tick is not None:
                if flags.any():
                    on_tick(self, np.flatnonzero(flags & 1), np.flatnonzero(flags & 2))
                else:
                    on_tick(self, _NO_ROWS, _NO_ROWS)
        self.live = True
        return head
