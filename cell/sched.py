"""A process's place on the machine: pinned to CPUs, at a real-time priority where the OS allows it.

SCHED_FIFO makes the kernel run a process the moment it becomes runnable
(its timer fires, a datagram arrives), ahead of every normal process, which
is what a 2 ms robot tick needs on a loaded machine; CFS alone lets a busy
neighbour hold the core for a time slice of several milliseconds.  Where
SCHED_FIFO is refused (no CAP_SYS_NICE, an RLIMIT_RTPRIO of 0, a cgroup with
no real-time budget) the process falls back to a nice value, and where that
is refused too it runs as it is: what it got is reported, never hidden.
Everything is applied to every thread the process has, and threads started
later (ZeroMQ's I/O thread) inherit it.  A cell's real-time group (place_loops)
gives its SCHED_FIFO priority to its native loops alone, as they start
(hand_over): its Python stays at the normal policy from the first import on.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import threading
import time

from cell import rtbudget

log = logging.getLogger("cell.sched")

_POLICY = {
    getattr(os, "SCHED_OTHER", 0): "normal",
    getattr(os, "SCHED_FIFO", 1): "fifo",
    getattr(os, "SCHED_RR", 2): "rr",
    getattr(os, "SCHED_BATCH", 3): "batch",
    getattr(os, "SCHED_IDLE", 5): "idle",
}


_REALTIME = (getattr(os, "SCHED_FIFO", 1), getattr(os, "SCHED_RR", 2))


def _policy() -> int:
    """This thread's scheduling policy, without SCHED_RESET_ON_FORK."""
    return os.sched_getscheduler(0) & 0xFF


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def place(cpus: list[int], rt_priority: int, nice: int) -> list[str]:
    """Pin this process to `cpus` ([] = leave as is) and make it SCHED_FIFO `rt_priority` (0 = leave
    the policy as is) or, failing that, nice `nice`; return what could not be done, in words."""
    problems: list[str] = []
    if cpus and hasattr(os, "sched_setaffinity"):
        # the machine's CPUs, not the ones this process inherited: a parent's narrower mask is no limit
        online = set(range(os.cpu_count() or 1))
        use = set(cpus) & online
        if not use:
            problems.append(f"CPUs {cpus} are not among this machine's {sorted(online)}: not pinned")
        else:
            if use != set(cpus):
                problems.append(
                    f"CPUs {sorted(set(cpus) - online)} do not exist here: pinned to {sorted(use)}"
                )
            try:
                for tid in _threads():
                    os.sched_setaffinity(tid, use)
            except OSError as exc:  # e.g. outside the cgroup's cpuset
                problems.append(f"CPUs {sorted(use)} refused ({exc.strerror}): not pinned")
    if rt_priority and hasattr(os, "sched_setscheduler"):
        try:
            for tid in _threads():
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(rt_priority))
            if why := keep_cpus_awake():
                problems.append(why)
            # (the nice value too, for what such a thread does at the normal policy: Spin's polls)
            with contextlib.suppress(OSError):
                for tid in _threads():
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
            return problems
        except OSError as exc:
            problems.append(f"SCHED_FIFO {rt_priority} refused ({exc.strerror}): nice {nice} instead")
    if nice:
        try:
            for tid in _threads():
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        except OSError as exc:
            problems.append(f"nice {nice} refused ({exc.strerror}): normal priority")
    return problems


HELD_NS = 5_000_000  # a real-time thread runnable this long without running was held back
CHECK_NS = 1_000_000  # Held.check reads the kernel's figure at most this often


class Held:
    """When the scheduler held this (real-time) thread back: runnable, yet not run.

    The kernel's RT throttling (sched_rt_runtime_us: SCHED_FIFO threads get at most 950 ms of each
    second of a CPU, by default) stops every real-time thread of a CPU that used up its share for
    the rest of that second, 20-50 ms in which robots miss ticks and modules their cycles.  It says
    so in dmesg once per boot only; this sees each time: the thread's time spent waiting on a run
    queue (/proc/thread-self/schedstat, field 2) growing by HELD_NS or more between two checks.  At
    FIFO priority on a core of its own a thread waits microseconds for the CPU otherwise, and a VM
    whose vCPU did not run is not counted (it was not waiting on the guest's run queue).  Call
    check() on every wake of the thread's loop (it costs about 2.5 us, at most every CHECK_NS).
    Only a wait that filled at least half the time since the last check counts: a loop checked
    seldom (a busy one that rarely reaches its check) sums many short waits behind other real-time
    threads, which is no hold (a flooded hub once "held" 9.5 s over 28 s of fuzzing)."""

    def __init__(self, tid: int = 0) -> None:
        """tid: another thread of this process to watch (a native loop's), 0: the calling one."""
        path = f"/proc/self/task/{tid}/schedstat" if tid else "/proc/thread-self/schedstat"
        self.tid = tid or threading.get_native_id()
        try:  # (open for the process's life: one pread a check)
            self._fd = os.open(path, os.O_RDONLY)
        except OSError:  # (not Linux, or no CONFIG_SCHED_INFO)
            self._fd = -1
        self.events = 0  # times held back
        self.total_ns = 0
        self.max_ns = 0
        self.next_ns = 0  # (the caller's clock: the next check due)
        self._delay = self._read()
        self._at = 0  # (the caller's clock: the last check; the first one only takes a baseline)

    def _read(self) -> int:
        if self._fd < 0:
            return 0
        try:
            return int(os.pread(self._fd, 64, 0).split()[1])
        except (OSError, IndexError, ValueError):
            return self._delay

    def check(self, now_ns: int) -> int:
        """How long the thread was held back since the last check (ns; 0: not HELD_NS)."""
        self.next_ns = now_ns + CHECK_NS
        delay = self._read()
        grew, self._delay = delay - self._delay, delay
        since, self._at = now_ns - self._at, now_ns
        if grew < HELD_NS or 2 * grew < since:
            return 0
        self.events += 1
        self.total_ns += grew
        self.max_ns = max(self.max_ns, grew)
        # (when and where, for the log: the counters say how often and how long; a hold that comes
        # with every real-time thread of its CPU held is the kernel's throttling, one alone is not)
        ms, where = grew / 1e6, _where(self.tid)
        log.info("real-time thread %d was held %.0f ms on the run queue (%s)", self.tid, ms, where)
        return grew

    def counters(self, prefix: str = "rt.") -> dict[str, float]:
        return {
            f"{prefix}held": self.events,
            f"{prefix}held_ms": self.total_ns / 1e6,
            f"{prefix}held_max_ms": self.max_ns / 1e6,
        }


def _where(tid: int) -> str:
    """A thread's CPU and policy now, in words (its /proc stat's processor and policy fields)."""
    try:
        with open(f"/proc/self/task/{tid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        cpu, prio, policy = int(fields[36]), int(fields[37]), int(fields[38])
    except (OSError, IndexError, ValueError):
        return "where: unknown"
    return f"on CPU {cpu}, {_POLICY.get(policy, policy)}" + (f" {prio}" if prio else "")


class HeldThreads:
    """Held for several threads of this process (each native loop that kept its real-time priority:
    a robots process may tick more than one group), counted as one."""

    def __init__(self) -> None:
        self.threads: list[Held] = []
        self.next_ns = 0

    def add(self, tid: int) -> None:
        if all(h.tid != tid for h in self.threads):
            self.threads.append(Held(tid))

    def check(self, now_ns: int) -> int:
        self.next_ns = now_ns + CHECK_NS
        return max((h.check(now_ns) for h in self.threads), default=0)

    def counters(self, prefix: str = "rt.") -> dict[str, float]:
        hs = self.threads
        return {
            f"{prefix}held": sum(h.events for h in hs),
            f"{prefix}held_ms": sum(h.total_ns for h in hs) / 1e6,
            f"{prefix}held_max_ms": max((h.max_ns for h in hs), default=0) / 1e6,
        }


class Spin:
    """A loop that polls without sleeping (the SnP cycles: a wake from epoll costs as much as the
    work) must not do so at a real-time priority all the time: the kernel's RT throttling would stop
    it, and every other real-time thread of its CPU, for the rest of the second.  Nor at the normal
    policy: any busy normal process then takes the CPU from a cycle in flight (a CPU hog: 6% of the
    C cycle's exchanges missed where 0.7% were).  It sleeps at its real-time priority (a wake comes
    at once) and polls at it while its polling stays within BUDGET_NS of each WINDOW_NS (90 ms of
    each 100: the kernel's 95% is never reached, the CPU's normal threads get 10 ms of every 100),
    past that at the normal policy and its nice value until the next window.  poll() before a poll
    without sleeping, sleep() before a sleep or when done.  At most two system calls a cycle;
    nothing at all in a thread that is not real-time.  The C cycles' spin_t (cell/snp/wire.h) is
    the same."""

    WINDOW_NS = 100_000_000
    BUDGET_NS = 90_000_000

    def __init__(self) -> None:
        rt = realtime()
        self.policy = _policy() if rt else 0  # (the one to go back to)
        self.prio = os.sched_getparam(0).sched_priority if rt else 0
        self.low = False
        self.window = self.polled = self.last = 0  # (the budget's window, ns polled in it, last poll)

    def poll(self) -> None:
        if not self.prio:
            return
        now = time.monotonic_ns()
        if self.last:
            self.polled += now - self.last  # (polling since the last call)
        self.last = now
        if now - self.window >= self.WINDOW_NS:
            self.window, self.polled = now, 0
        over = self.polled >= self.BUDGET_NS
        if over != self.low:
            self._set(over)

    def sleep(self) -> None:
        if self.last:
            self.polled += time.monotonic_ns() - self.last
            self.last = 0
        if self.low:
            self._set(False)

    def _set(self, low: bool) -> None:
        try:
            if low:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            else:
                os.sched_setscheduler(0, self.policy, os.sched_param(self.prio))
            self.low = low
        except OSError:
            pass


_PM_QOS: list[int] = []  # the open /dev/cpu_dma_latency request (held for the process's life)


def keep_cpus_awake() -> str:
    """Ask the kernel to keep every CPU out of its deeper idle states while this process lives (PM
    QoS: 0 us written to /dev/cpu_dma_latency and the file kept open, as cyclictest and tuned's
    latency-performance profile do); "" if done, else why not (needs root).

    A real-time thread woken from an idle CPU waits for that CPU to leave its idle state first; in a
    VM whose idle vCPUs halt (the haltpoll driver here), that was the most of a 1 ms timer's
    lateness: p50 63 us, p99 0.3-2.5 ms on an idle machine at SCHED_FIFO 80, against p50 28-39 us,
    p99 59-90 us with the request held (a clock_nanosleep loop in C, 5,000 wakes a CPU)."""
    if _PM_QOS:
        return ""
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        return f"CPUs may idle deeply: /dev/cpu_dma_latency refused ({exc.strerror})"
    try:
        os.write(fd, (0).to_bytes(4, "little"))
    except OSError as exc:
        os.close(fd)
        return f"CPUs may idle deeply: /dev/cpu_dma_latency refused ({exc.strerror})"
    _PM_QOS.append(fd)
    return ""


def realtime() -> bool:
    """Whether this thread runs at a real-time policy (SCHED_FIFO or SCHED_RR)."""
    return hasattr(os, "sched_getscheduler") and _policy() in _REALTIME


# the threads of this process that keep its real-time priority (native per-tick or per-packet
# loops) once hand_over() moved the rest of it to the normal policy
RT_THREADS: set[int] = set()
RT_NICE = -10  # what the rest of a real-time process runs at, after hand_over()
# the SCHED_FIFO priority this process's group asked for (place_loops), for its native loops; 0: none
LOOP_PRIORITY = 0
REST_PRIORITY = 0  # SCHED_FIFO of the process's other threads (rest_at), 0: the normal policy


def place_loops(cpus: list[int], rt_priority: int, nice: int) -> list[str]:
    """Place a real-time group's process: pinned to `cpus`, every thread at the normal policy (at
    RT_NICE, or `nice` with no `rt_priority`), `rt_priority` kept for its native loops, which take
    it as they start (hand_over).  Its Python (imports, models, config) never runs at real-time
    priority: a process starting at SCHED_FIFO held the data plane's loop, on the same core, for up
    to 340 ms.  What could not be done, in words."""
    global LOOP_PRIORITY
    problems = place(cpus, 0, RT_NICE if rt_priority else nice)
    if rt_priority and hasattr(os, "sched_setscheduler"):
        LOOP_PRIORITY = rt_priority
        if why := keep_cpus_awake():
            problems.append(why)
    return problems


def hand_over(tid: int, nice: int = RT_NICE) -> list[str]:
    """Give thread `tid` (a native loop: cell/robot/tick.c, cell/dataplane/native.c) this process's
    real-time priority (LOOP_PRIORITY, or the whole process's if place() made it real-time) and leave
    every other thread (Python's, ZeroMQ's) at the normal policy at `nice`: nothing per bus message
    or per client runs at real-time priority, and nothing but the native loops can spend the CPU's
    real-time budget (RT throttling holds every real-time thread of a CPU once they used it up).
    Threads started later inherit the normal policy; after rest_at(), the other threads stay at
    its SCHED_FIFO priority instead, under the native loops.  Return what could not be done, in
    words (a process that asked for no real-time priority: nothing to hand over)."""
    if tid <= 0 or not (LOOP_PRIORITY or realtime() or RT_THREADS):
        return []
    rtbudget.exempt(tid)  # (where a budget watches the rest of the process: not this loop)
    if LOOP_PRIORITY and tid not in RT_THREADS:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(LOOP_PRIORITY))
        except OSError as exc:
            return [f"SCHED_FIFO {LOOP_PRIORITY} refused for native loop {tid} ({exc.strerror})"]
    RT_THREADS.add(tid)
    return _rest(REST_PRIORITY, nice)


def rest_at(priority: int) -> list[str]:
    """From now on, every thread of this process but its native loops at SCHED_FIFO `priority` (at
    most LOOP_PRIORITY): a loop that must run real-time in Python (a robots group ticking in Python,
    the numpy data plane, a control plane over every normal process).  Only in a process whose
    group asked for real time; what could not be done, in words."""
    global REST_PRIORITY
    if not LOOP_PRIORITY:  # (a process place() made real-time as a whole is so already)
        return []
    REST_PRIORITY = max(REST_PRIORITY, max(1, min(priority, LOOP_PRIORITY - 1)))  # (under the loops)
    problems = _rest(REST_PRIORITY, RT_NICE)
    if not problems:  # (real-time granted: within its budget, never the kernel's RT throttling)
        problems = rtbudget.start(LOOP_PRIORITY, REST_PRIORITY, RT_NICE, RT_THREADS)
    return problems


def _rest(priority: int, nice: int) -> list[str]:
    """Every thread but the native loops at SCHED_FIFO `priority`, or the normal policy at `nice`."""
    problems: list[str] = []
    for t in _threads():
        if t in RT_THREADS or t == rtbudget.watcher():
            continue
        try:
            if priority > 0:
                os.sched_setscheduler(t, os.SCHED_FIFO, os.sched_param(priority))
            else:
                os.sched_setscheduler(t, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, t, nice)
        except OSError as exc:
            problems.append(
                f"thread {t}: SCHED_FIFO {priority} refused ({exc.strerror})"
                if priority > 0
                else f"thread {t}: normal policy refused ({exc.strerror})"
            )
    return problems


def describe() -> str:
    """How the OS schedules this process now: 'fifo 70, cpu 1', 'nice -5, cpus 0-1', 'normal, cpus 0-1'."""
    if not hasattr(os, "sched_getscheduler"):
        return "unknown"
    policy = _policy()
    name = _POLICY.get(policy, f"policy {policy}")
    rt_thread = _rt_thread_policy()
    if rt_thread and rtbudget.watcher():  # (the rest real-time within its budget: at times normal)
        what = f"{rt_thread} native, rest fifo {REST_PRIORITY}"
    elif rt_thread and policy in _REALTIME:  # (the loop native, the rest of the process under it)
        what = f"{rt_thread} native, rest {name} {os.sched_getparam(0).sched_priority}"
    elif rt_thread:  # (the real-time loop is native, the rest of the process normal)
        what = f"{rt_thread} native, rest nice {os.getpriority(os.PRIO_PROCESS, 0)}"
    elif rtbudget.watcher():  # (its Python real-time within its budget, no native loop: XDP's control)
        what = f"fifo {REST_PRIORITY}"
    elif policy in _REALTIME:
        what = f"{name} {os.sched_getparam(0).sched_priority}"
    else:
        niceness = os.getpriority(os.PRIO_PROCESS, 0)
        what = f"nice {niceness}" if niceness else name
    cpus = sorted(os.sched_getaffinity(0))
    return f"{what}, {'cpu' if len(cpus) == 1 else 'cpus'} {_ranges(cpus)}"


def _rt_thread_policy() -> str:
    """'fifo 70' for the native real-time threads (hand_over), "" if none runs."""
    for tid in sorted(RT_THREADS):
        try:
            policy = os.sched_getscheduler(tid) & 0xFF
            return f"{_POLICY.get(policy, policy)} {os.sched_getparam(tid).sched_priority}"
        except OSError:  # (it ended)
            continue
    return ""


def _ranges(cpus: list[int]) -> str:
    out: list[str] = []
    for c in cpus:
        if out and out[-1].split("-")[-1] == str(c - 1):
            out[-1] = f"{out[-1].split('-')[0]}-{c}"
        else:
            out.append(str(c))
    return ",".join(out)


def cpu_seconds() -> float:
    """CPU time this process has used so far, all its threads, user and system."""
    t = os.times()
    return t.user + t.system


def stolen_since(before: dict[int, float]) -> dict[int, float]:
    """Each CPU's steal since `before` (a stolen_seconds() reading), in seconds."""
    now = stolen_seconds()
    return {cpu: now[cpu] - before[cpu] for cpu in now if cpu in before}


def most_stolen(before: dict[int, float]) -> float:
    """The most any one CPU had stolen since `before` (a stolen_seconds() reading), s."""
    return max(stolen_since(before).values(), default=0.0)


def stolen_seconds() -> dict[int, float]:
    """Each CPU's steal time so far (/proc/stat): how long the hypervisor ran something else while
    this VM's vCPU had work.  A real-time thread cannot be held back more visibly: it was runnable
    and nothing in the guest ran instead, so no guest setting (priority, pinning) helps; {} where
    the kernel does not count it."""
    out: dict[int, float] = {}
    try:
        with open("/proc/stat") as f:
            for line in f:
                name, *fields = line.split()
                if name.startswith("cpu") and name != "cpu" and len(fields) >= 8:
                    out[int(name[3:])] = int(fields[7]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError):
        return {}
    return out


def process_cpu_seconds(pid: int) -> float:
    """Another process's user + system CPU seconds so far (/proc/<pid>/stat); NaN once it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except OSError:
        return float("nan")


def settle_heap() -> None:
    """Collect what start-up left and move the rest out of the garbage collector's sight.

    A full (generation 2) pass walks every object the process holds: with numpy and the cell's
    modules loaded that is 5-13 ms on this machine kind, ten 1 ms cycles lost at once, every few
    seconds, in a loop that allocates a little per cycle.  Frozen, start-up's objects are never
    walked again and a pass costs what the loop itself made since.  Call it once, in a process of
    its own, after setting up and before the real-time loop (it freezes the whole process)."""
    gc.collect()
    gc.freeze()
