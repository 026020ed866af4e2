"""`cell bench dataplane`: status answered within the command window, next to its baselines.

A load generator (one process, one core) plays R robots x 6 joints at 500 Hz:
every 2 ms it sends each joint's status with seq = the tick number (UDP GSO,
one socket) and timestamps every answer as it arrives (UDP GRO), so each
command's status-to-command time is exact.  On the other core runs one of:

- dataplane: the real service's packet path (cell.dataplane.plane.DataPlane),
  every robot following a trajectory, so every packet takes the full pipeline;
- reflector: the same batched UDP I/O and no pipeline (this machine's limit);
- naive: the same controller written the obvious way, an asyncio
  DatagramProtocol handling one datagram at a time in floating point.

A trial passes when >= 99% of status datagrams are answered within the
command window (8 ms); R grows until one fails.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import queue
import select
import signal
import socket
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell.bench import pinned
from cell.bench.dataplane_targets import TARGETS
from cell.bench.registry import Bench, Failed, Figures, log, register
from cell.bench.xdpnet import xdp_switch
from cell.config import DATAPLANE_BACKENDS
from cell.robot import datagram, udp
from cell.robot.datagram import Kind
from cell.sched import process_cpu_seconds
from cell.timer import realtime_offset

WINDOW_NS = 8_000_000
PERIOD_NS = 2_000_000
ON_TIME = 0.99
PAPER = (
    "the paper (Tofino, Sec. 7.1): 0.6-1.3 us status to command at 64 B; 500-1000 robots on one switch "
    "(Sec. 7.5); the x86 ROS driver 45 arms on 12 cores (App. B); table churn does not affect latency"
)


# --- the load generator (this process) -----------------------------------------------------------


@dataclass
class Trial:
    """One load of `robots` robots (x 6 joints x 500 Hz) against a target: what came back, and when."""

    target: str
    robots: int
    rate: int  # status datagrams/s offered
    sent: int = 0
    answered: int = 0
    on_time: int = 0  # answered within the command window
    on_time_fraction: float = 0.0
    generator_late_ticks: int = 0  # the load's own ticks more than a period late (this VM's stalls)
    sink_datagrams: int = 0  # ordinary traffic counted meanwhile (cell.bench.background)
    sink_bytes: int = 0
    span_s: float = 0.0
    p50_us: float = float("nan")  # status to command (kernel stamps)
    p99_us: float = float("nan")
    max_us: float = float("nan")
    cpu_cores: float = float("nan")  # the target's CPU over the load (its processes', in cores)
    update_ms: list[float] = field(default_factory=list)  # each controller update's time (+updates)
    hold_ms: list[float] = field(default_factory=list)  # the packet path held by each update, at most
    ok: bool = False  # >= ON_TIME answered within the window
    limit: str = ""  # why the target refused this load (its capacity), if it did


@dataclass
class Search:
    """sustained(): the best passing trial of a target, every trial run, and the capacity it met."""

    target: str
    best: Trial | None
    trials: list[Trial]
    limit: str | None = None

    @property
    def rate(self) -> float:
        return float(self.best.rate) if self.best is not None else 0.0


Address = tuple[str, int]


def load(addr: Address | list[Address], robots: int, seconds: float, bind: str = "127.0.0.1") -> Trial:
    """Play `robots` robots at 500 Hz against addr (or a list: each robot its own) for `seconds`;
    status-to-command times of every answer."""
    with pinned(0):
        return _load(addr, robots, seconds, bind)


def _load(
    addr: Address | list[Address],
    robots: int,
    seconds: float,
    bind: str = "127.0.0.1",
    sink: socket.socket | None = None,
) -> Trial:
    """As load(); bind: the robots' address; sink: a socket whose datagrams are counted meanwhile
    (ordinary traffic forwarded to the robots' host, cell.bench.background)."""
    sock = udp.open_socket(bind, timestamps=True)
    sender = udp.Sender(sock, datagram.SIZE)
    # answers are timed by the kernel's receive stamp (CLOCK_REALTIME, taken to monotonic), and each
    # status from when its own GSO send left: the generator's wake-ups and send loop do not count
    offset = realtime_offset()
    n = robots * 6
    recs = datagram.empty(n)
    datagram.pack(
        recs, np.repeat(np.arange(1, robots + 1), 6), np.tile(np.arange(6), robots), Kind.STATUS, 0, 0.0, 0.0
    )
    raw = recs.view(np.uint8).data
    chunk = 64 * datagram.SIZE  # GSO segments per call
    if isinstance(addr, list):  # a driver per robot: one send of its 6 joints each
        chunk = 6 * datagram.SIZE
    ticks = int(seconds * 1e9 / PERIOD_NS)
    sends = -(-len(raw) // chunk)
    sent_at = np.zeros((ticks + 1, sends), np.int64)
    arrivals: list[tuple[int, bytes]] = []  # decoded after the run: the receive loop must stay cheap
    poller = select.epoll()
    poller.register(sock.fileno(), select.EPOLLIN)
    sunk = [0, 0]  # datagrams, bytes
    if sink is not None:
        poller.register(sink.fileno(), select.EPOLLIN)

    def drain() -> None:
        _drain(sock, arrivals, offset)
        if sink is not None:
            while (got := udp.recv_batch(sink)) is not None:
                sunk[0] += -(-len(got[0]) // max(got[1], 1))
                sunk[1] += len(got[0])

    drain()  # what the sink got before the span does not count
    sunk[:] = [0, 0]
    start = time.monotonic_ns() + 50_000_000
    sent = late_ticks = 0
    try:
        for k in range(1, ticks + 1):
            due = start + k * PERIOD_NS
            while (now := time.monotonic_ns()) < due:  # take answers until the next tick is due
                if poller.poll(max(0.0, (due - now) / 1e9 - 0.0002)):
                    drain()
            if now - due > PERIOD_NS:
                late_ticks += 1
            recs["seq"] = k
            for c, i in enumerate(range(0, len(raw), chunk)):
                sent_at[k, c] = time.monotonic_ns()
                to = addr[c] if isinstance(addr, list) else addr
                sent += sender.send(raw[i : i + chunk], to)
        span_ns, sunk_in_span = time.monotonic_ns() - start + 50_000_000, list(sunk)  # the sink's, over it
        end = time.monotonic_ns() + 500_000_000
        while time.monotonic_ns() < end and _received(arrivals) < sent:  # the last answers, if they come
            if poller.poll(0.001):
                drain()
    finally:
        poller.close()
        sock.close()
    lat = []
    for at, data in arrivals:
        if len(data) % datagram.SIZE:
            continue
        recs_in = datagram.view(data)
        seqs = recs_in["seq"].astype(np.int64)
        send = ((recs_in["robot_id"].astype(np.int64) - 1) * 6 + recs_in["joint_id"]) * datagram.SIZE // chunk
        ok = (seqs > 0) & (seqs <= ticks) & (send >= 0) & (send < sends)
        lat.append(at - sent_at[seqs[ok], send[ok]])
    times = np.concatenate(lat) if lat else np.zeros(0, np.int64)
    answered = times.size
    on_time = int((times <= WINDOW_NS).sum())
    out = Trial(
        "",
        robots,
        n * 500,
        sent=sent,
        answered=answered,
        on_time=on_time,
        on_time_fraction=on_time / max(sent, 1),
        generator_late_ticks=late_ticks,
        sink_datagrams=sunk_in_span[0],
        sink_bytes=sunk_in_span[1],
        span_s=span_ns / 1e9,
    )
    if times.size:
        out.p50_us = float(np.percentile(times, 50)) / 1e3
        out.p99_us = float(np.percentile(times, 99)) / 1e3
        out.max_us = float(times.max()) / 1e3
    return out


def _received(arrivals: list[tuple[int, bytes]]) -> int:
    return sum(len(data) for _, data in arrivals) // datagram.SIZE


def _drain(sock: socket.socket, arrivals: list[tuple[int, bytes]], offset: int) -> None:
    """Every answer waiting, with its kernel receive time on the monotonic clock (offset: realtime
    minus monotonic; a burst without a stamp counts as received now)."""
    while (got := udp.recv_batch(sock)) is not None:
        arrivals.append((got[3] - offset if got[3] else time.monotonic_ns(), got[0]))


def trial(target: str, robots: int, seconds: float = 2.0, net: Any = None) -> Trial:
    """One run of `robots` robots against a target; net: the switch (XdpConfig) of the xdp targets."""
    ctx = mp.get_context("spawn")
    out, stop = ctx.Queue(), ctx.Event()
    args = (robots, out, stop) if net is None else (robots, out, stop, net)
    proc = ctx.Process(target=TARGETS[target], args=args, daemon=True)
    proc.start()
    addr = _address(proc, out)
    if isinstance(addr, str):  # it could not take this many robots: the search's limit, not a traceback
        proc.join(10)
        if proc.is_alive():
            proc.kill()
        return Trial(target, robots, robots * 6 * 500, limit=addr)
    dest: Address | list[Address]
    if isinstance(addr, dict):  # (a target of many processes: each arm's address, their pids)
        pids, dest = addr["pids"], [tuple(a) for a in addr["addrs"]]
    else:
        assert proc.pid is not None  # (started)
        pids, dest = [proc.pid], addr
    cpu0, t0 = sum(process_cpu_seconds(p) for p in pids), time.monotonic()
    try:
        result = load(dest, robots, seconds, bind="127.0.0.1" if net is None else net.host_addr)
        result.cpu_cores = (sum(process_cpu_seconds(p) for p in pids) - cpu0) / (time.monotonic() - t0)
    finally:
        stop.set()
    if target.startswith(("dataplane", "xdp")) and target != "xdp-reflector":
        try:
            stats = out.get(timeout=30)
            result.update_ms, result.hold_ms = stats.get("update_ms", []), stats.get("hold_ms", [])
        except queue.Empty:
            pass
    proc.join(10)
    result.target = target
    result.ok = result.on_time_fraction >= ON_TIME
    return result


def _address(proc: Any, out: Any, timeout: float = 60.0) -> Address | dict | str:
    """The target's address once it is up, or why it is not (it refused this many robots, died, or
    did not come up in time)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            got = out.get(timeout=0.5)
        except queue.Empty:
            if not proc.is_alive():
                return f"the target died (exit code {proc.exitcode})"
            continue
        if isinstance(got, dict):
            return got if "addrs" in got else got["error"]
        return tuple(got)
    return f"the target did not come up in {timeout:.0f} s"


def sustained(target: str, start: int, seconds: float, log: Any = None, net: Any = None) -> Search:
    """The most status datagrams/s answered within the window: R doubles until a trial fails, then two
    bisections narrow it down.  A failed trial is run once more (this VM stalls for milliseconds now
    and then), so a rate counts when one of two trials passes."""
    trials: list[Trial] = []
    best: Trial | None = None

    def passes(r: int) -> bool:
        nonlocal best
        for _ in range(2):
            t = trial(target, r, seconds, net)
            trials.append(t)
            if log:
                log(t)
            if t.ok:
                if best is None or t.rate > best.rate:
                    best = t
                return True
            if t.limit:  # (past its capacity: a second try would only say it again)
                return False
        return False

    ok, r = 0, start
    while passes(r):
        ok, r = r, r * 2
    bad = r
    for _ in range(2):
        mid = (ok + bad) // 2
        if mid <= ok or trials[-1].limit:  # (a target past its capacity: no use bisecting)
            break
        if passes(mid):
            ok = mid
        else:
            bad = mid
    limit = next((f"{t.robots} robots: {t.limit}" for t in trials if t.limit), None)
    return Search(target, best, trials, limit)


def format_trial(t: Trial) -> str:
    if t.limit:
        return f"{t.target:>10} {t.robots:>4} robots: over the target's capacity ({t.limit})"
    verdict = "ok  " if t.ok else "FAIL"
    return (
        f"{t.target:>10} {t.robots:>4} robots ({t.rate:>9,} status/s): {verdict} "
        f"on time {100 * t.on_time_fraction:6.2f}%  p50/p99 {t.p50_us:7.0f}/"
        f"{t.p99_us:7.0f} us  generator late ticks {t.generator_late_ticks}"
    )


@dataclass
class Run:
    """What `cell bench dataplane` measured: each target's search, latency at 10/100/300 robots, and
    the same 100-robot load without and with a controller's updates; with --backend xdp also the
    latency with the program on the sender's core, and the issue's figures flat (summary)."""

    throughput: dict[str, Search]
    latency: list[Trial]
    updates: tuple[Trial, Trial]  # (quiet, with updates)
    latency_same_core: list[Trial] = field(default_factory=list)
    summary: dict[str, float] = field(default_factory=dict)

    def best(self, target: str) -> float:
        return self.throughput[target].rate

    def to_json(self) -> dict[str, Any]:
        """The JSON line: the summary's flat figures first (issue 18's keys), then every trial."""
        out = asdict(self)
        return {**out.pop("summary"), **out}


def run(seconds: float = 2.0, log: Any = None) -> Run:
    throughput = {
        t: sustained(t, s, seconds, log) for t, s in (("reflector", 20), ("dataplane", 20), ("naive", 5))
    }
    latency = [trial("dataplane", r, seconds) for r in (10, 100, 300)]
    # updates under load: the same load with and without a controller's updates each second
    quiet, busy = (trial(t, 100, max(seconds, 3.5)) for t in ("dataplane", "dataplane+updates"))
    for t in [*latency, quiet, busy] if log else ():
        log(t)
    return Run(throughput, latency, (quiet, busy))


def _updates_line(quiet: Trial, busy: Trial) -> tuple[float, float, float]:
    """Mean and longest update (ms), and the longest the packet path was held (ms)."""
    ms, hold = busy.update_ms or [float("nan")], busy.hold_ms or [float("nan")]
    return float(np.mean(ms)), float(max(ms)), float(max(hold))


def format_result(result: Run) -> str:
    tp = result.throughput
    ref, dp, naive = result.best("reflector"), result.best("dataplane"), result.best("naive")
    lines = ["status datagrams/s answered >= 99% within the 8 ms command window (one core each side):"]
    lines += [
        f"  {name:>10}: {rate:>10,.0f}"
        + (f"  (stopped at its capacity, {tp[name].limit})" if tp[name].limit else "")
        for name, rate in (("reflector", ref), ("dataplane", dp), ("naive", naive))
    ]
    if ref and naive:
        lines.append(
            f"  dataplane = {100 * dp / ref:.0f}% of the reflector, {dp / naive:.1f}x the naive asyncio one"
        )
    lines.append("status-to-command time, robots x 6 joints x 500 Hz:")
    lines += [f"  {format_trial(t)}" for t in result.latency]
    quiet, busy = result.updates
    mean, longest, held = _updates_line(quiet, busy)
    lines.append(
        f"updates under load (100 robots; 1,600 inserts + 10,000 deletes a second, "
        f"{len(busy.update_ms)} updates): {mean:.1f} ms per update (max {longest:.1f}), the packet path "
        f"held at most {held:.2f} ms; p99 {busy.p99_us:.0f} us with vs {quiet.p99_us:.0f} us without "
        f"(ratio {busy.p99_us / quiet.p99_us:.2f})"
    )
    lines.append(PAPER)
    return "\n".join(lines)


# --- the XDP backend (--backend xdp) ------------------------------------------------------------


def run_xdp(seconds: float = 2.0, log: Any = None) -> Run:
    """The XDP data plane next to the bare XDP reflector (same switch) and the numpy data plane (on
    loopback, as the default cell runs it), under the same generator on core 0.  Throughput, latency
    and updates with the switch's program on core 1 (RPS), as the numpy target has core 1; latency
    once more with the program on the sender's core (cpu = -1, no cross-CPU hop).  Needs root, `ip`
    and the built object (SwitchError says which)."""
    from cell.dataplane.xdp.switch import switch_namespace

    def trials(targets: tuple[str, ...], robots: int, secs: float, net: Any) -> list[Trial]:
        out = [trial(t, robots, secs, net) for t in targets]
        for t in out if log else ():
            log(t)
        return out

    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)  # (so the namespace is removed)
    try:
        net = xdp_switch(cpu=1)
        with switch_namespace(net):
            throughput = {t: sustained(t, 20, seconds, log, net) for t in ("xdp-reflector", "xdp")}
            latency = [x for r in (10, 100, 300) for x in trials(("xdp",), r, seconds, net)]
            quiet, busy = trials(("xdp", "xdp+updates"), 100, max(seconds, 3.5), net)
        same_core = xdp_switch(cpu=-1)
        with switch_namespace(same_core):
            local = [x for r in (10, 100, 300) for x in trials(("xdp",), r, seconds, same_core)]
    finally:
        signal.signal(signal.SIGTERM, previous)
    throughput["dataplane"] = sustained("dataplane", 20, seconds, log)
    result = Run(throughput, latency, (quiet, busy), local)
    result.summary = xdp_summary(result)
    return result


def _exit_on_sigterm(*_: Any) -> None:
    raise SystemExit(143)


def xdp_summary(result: Run) -> dict[str, float]:
    """The figures issue 18 asks for, as flat keys."""
    ref, xdp, numpy = result.best("xdp-reflector"), result.best("xdp"), result.best("dataplane")
    out: dict[str, float] = {
        "xdp_status_per_s": xdp,
        "xdp_reflector_status_per_s": ref,
        "numpy_status_per_s": numpy,
        "xdp_of_reflector": xdp / ref if ref else 0.0,
        "xdp_over_numpy": xdp / numpy if numpy else 0.0,
    }
    for key, trials in (("", result.latency), ("same_core_", result.latency_same_core)):
        for t in trials:
            out[f"{key}p50_us_{t.robots}"] = t.p50_us
            out[f"{key}p99_us_{t.robots}"] = t.p99_us
            out[f"{key}on_time_{t.robots}"] = t.on_time_fraction
    quiet, busy = result.updates
    out["update_ms_mean"], out["update_ms_max"], out["hold_ms_max"] = _updates_line(quiet, busy)
    out["p99_us_updates"] = busy.p99_us
    out["p99_us_quiet"] = quiet.p99_us
    return out


def format_xdp(result: Run) -> str:
    s = result.summary
    lines = ["status datagrams/s answered >= 99% within the 8 ms command window (generator on core 0):"]
    ref, xdp, numpy = s["xdp_reflector_status_per_s"], s["xdp_status_per_s"], s["numpy_status_per_s"]
    lines += [
        f"  xdp-reflector: {ref:>10,.0f}   (bare XDP_TX: the switch's limit here)",
        f"            xdp: {xdp:>10,.0f}   = {100 * s['xdp_of_reflector']:.0f}% of the reflector",
        f"          numpy: {numpy:>10,.0f}   (xdp = {s['xdp_over_numpy']:.1f}x numpy)",
    ]
    lines += [
        f"  {name} stopped at its capacity: {t.limit}" for name, t in result.throughput.items() if t.limit
    ]
    lines += ["status-to-command time, robots x 6 joints x 500 Hz, XDP backend, its program on core 1:"]
    lines += [f"  {format_trial(t)}" for t in result.latency]
    lines.append("  ... and on the sender's core (cpu = -1: no cross-CPU hop):")
    lines += [f"  {format_trial(t)}" for t in result.latency_same_core]
    lines.append(
        f"updates under load (100 robots; 1,600 inserts + 10,000 deletes a second): "
        f"{s['update_ms_mean']:.1f} ms per update (max {s['update_ms_max']:.1f}), the kernel's packet path "
        f"held (gate closed) at most {s['hold_ms_max']:.3f} ms; p99 {s['p99_us_updates']:.0f} us with vs "
        f"{s['p99_us_quiet']:.0f} us without"
    )
    lines.append(PAPER)
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=2.0, help="length of each trial (default 2)")
    p.add_argument(
        "--backend",
        choices=["numpy", "xdp"],
        default="numpy",
        help="xdp: the XDP program in a switch namespace, next to a bare XDP reflector and numpy (root)",
    )


def _main(args: argparse.Namespace) -> Figures:
    def trial_log(trial: Trial) -> None:
        log(format_trial(trial))

    from cell.config import load_config

    dp = load_config(None).dataplane
    log(
        f"the data plane holds {dp.capacity:,} TPs and {dp.max_entities:,} robots ([dataplane] capacity, "
        "max_entities): a search stops there; robots double from 20 until a trial fails, then two bisections"
    )
    if DATAPLANE_BACKENDS[args.backend].in_kernel:
        from cell.dataplane.xdp.switch import SwitchError

        try:
            result = run_xdp(args.seconds, log=trial_log)
        except SwitchError as exc:
            print(f"cell bench dataplane: {exc}", file=sys.stderr)
            return Figures(Failed(str(exc)), exit_code=2)
        # the figures first, flat (the trials follow in the full result)
        return Figures(result, format_xdp(result))
    result = run(args.seconds, log=trial_log)
    return Figures(result, format_result(result))


register(
    Bench(
        "dataplane",
        "status/s answered within the command window, next to a bare reflector and a naive "
        "asyncio controller; latency at 10, 100, 300 robots",
        _arguments,
        _main,
    )
)
