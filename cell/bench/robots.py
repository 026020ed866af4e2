"""`cell bench robots`: the most robots one core runs at their status rate with < 0.1% late sends.

Each trial runs N robots of one backend in a process pinned to one core, with
a bare reflector pinned to the other core answering every status datagram
with a command (as the data plane would), for a few seconds; it passes when
fewer than 0.1% of status datagrams left a full period late (a missed tick
counts every robot's status of that period) and none was lost to a full
socket buffer.  N doubles until it fails, then a bisection finds the largest
passing N.  This VM stalls for milliseconds now and then whatever the load,
so each N gets a second trial before it counts as failed, and a one-robot
baseline in the same run shows how late the machine itself makes a tick.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import queue
import resource
import time
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from cell import aio
from cell.bench import pin
from cell.bench.registry import Bench, Figures, log, register
from cell.config import load_config
from cell.jsonfields import OMIT_IF_NONE, JsonFields
from cell.robot import datagram, udp
from cell.robot.datagram import Kind

LATE_LIMIT = 0.001
TRIES = 2  # trials of one N before it counts as failed (the VM stalls at random)


def reflector(out: Any, stop: Any, answer: bool = True, core: int = 1) -> None:
    """Answer every status datagram with a command (velocity 0, seq and position echoed), or just count."""
    pin(core)
    sock = udp.open_socket("127.0.0.1")
    sender = udp.Sender(sock, datagram.SIZE)
    out.put(sock.getsockname())
    import select

    poller = select.epoll()
    poller.register(sock.fileno(), select.EPOLLIN)
    answered = received = 0
    while not stop.is_set():
        if not poller.poll(0.1):
            continue
        while (got := udp.recv_batch(sock)) is not None:
            data, seg, sender_addr, _ = got
            if seg != datagram.SIZE or len(data) % seg:
                continue
            received += len(data) // seg
            if not answer:
                continue
            recs = datagram.view(bytearray(data))
            recs["kind"] = Kind.COMMAND
            recs["velocity"] = 0
            answered += sender.send(recs.view(np.uint8).data, sender_addr)
    out.put((received, answered))
    sock.close()


def _trial_child(
    backend: str, n: int, seconds: float, dataplane: str, out: Any, core: int = 0, socket: str = "own"
) -> None:
    pin(core)
    from cell.robot.emulator import RobotGroup

    robots = [
        {
            "id": i + 1,
            "name": f"b{i}",
            "skill_port": 20000 + i,
            "backend": backend,
            "truth_hz": 0,
            "socket": socket,
        }
        for i in range(n)
    ]
    cfg = load_config(overrides={"robots": robots})
    group = RobotGroup(cfg.robots, dataplane)

    async def main() -> None:
        import asyncio

        task = asyncio.ensure_future(group.run())
        await asyncio.sleep(0.3)  # warm-up, not measured
        base = group.counters.as_dict()
        group.counters.lateness.clear()
        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.monotonic()
        await asyncio.sleep(seconds)
        elapsed = time.monotonic() - t0
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        end = group.counters.as_dict()
        task.cancel()
        delta = {k: end[k] - base.get(k, 0) for k in end if not k.startswith("lateness")}
        delta.update({k: v for k, v in end.items() if k.startswith("lateness")})
        cpu = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
        out.put({**delta, "seconds": elapsed, "cpu": cpu / elapsed})

    try:
        aio.run(main())
    finally:
        group.close()


def late_statuses(
    late_sends: float, missed_ticks: float, robots: int, seconds: float, status_hz: int = 500, joints: int = 6
) -> tuple[float, float]:
    """(status datagrams that left late, those due) over `seconds`: a missed tick is a whole period of
    every robot's status not sent on time."""
    return late_sends + missed_ticks * robots * joints, robots * joints * seconds * status_hz


def trial(
    backend: str, n: int, seconds: float = 3.0, answer: bool = True, socket: str = "own"
) -> dict[str, float]:
    ctx = mp.get_context("spawn")
    out, stop = ctx.Queue(), ctx.Event()
    refl = ctx.Process(target=reflector, args=(out, stop, answer), daemon=True)
    refl.start()
    host, port = out.get(timeout=30)
    child = ctx.Process(
        target=_trial_child, args=(backend, n, seconds, f"{host}:{port}", out, 0, socket), daemon=True
    )
    child.start()
    try:
        result = out.get(timeout=seconds + 60)
    except queue.Empty:
        result = {}
    child.join(10)
    stop.set()
    received, answered = out.get(timeout=10)
    refl.join(5)
    sent = result.get("status_sent", 0)
    late_count, expected = late_statuses(
        result.get("late_sends", 0),
        result.get("missed_ticks", 0),
        n,
        result.get("seconds", seconds),
        load_config().robot_defaults.status_hz,
    )
    late = late_count / expected if result else 1.0
    unsent = result.get("status_unsent", 1)
    ok = bool(result) and late < LATE_LIMIT and unsent == 0 and sent >= 0.99 * expected
    return {
        **result,
        "robots": n,
        "socket": socket,
        "late_fraction": late,
        "expected": expected,
        "received": received,
        "answered": answered,
        "ok": ok,
    }


@dataclass
class MaxRobots(JsonFields):
    """One backend's (and socket's) most robots, found by bisection; its trials as trial() gave them."""

    backend: str
    socket: str
    max_robots: int
    best: dict[str, Any] | None
    trials: list[dict[str, Any]]


@dataclass
class RobotsResult(JsonFields):
    """The 1-robot baseline (a trial), and each backend's most robots with a socket a robot (own) and
    one for the group (_shared): those it ran."""

    baseline: dict[str, Any]
    answered: bool
    kinematic: MaxRobots | None = field(default=None, metadata=OMIT_IF_NONE)
    kinematic_shared: MaxRobots | None = field(default=None, metadata=OMIT_IF_NONE)
    mujoco: MaxRobots | None = field(default=None, metadata=OMIT_IF_NONE)
    mujoco_shared: MaxRobots | None = field(default=None, metadata=OMIT_IF_NONE)

    def backends(self) -> dict[str, MaxRobots]:
        """The backends that ran, by key ("kinematic", "mujoco_shared", ...)."""
        return {f.name: r for f in fields(self) if isinstance(r := getattr(self, f.name), MaxRobots)}


def max_robots(
    backend: str, start: int, seconds: float, log: Any = None, answer: bool = True, socket: str = "own"
) -> MaxRobots:
    trials: list[dict[str, Any]] = []

    def run(n: int) -> bool:
        for _ in range(TRIES):
            r = {"backend": backend, **trial(backend, n, seconds, answer, socket)}
            trials.append(r)
            if log:
                log(r)
            if r["ok"]:
                return True
        return False

    lo, hi = 0, start
    while run(hi):
        lo, hi = hi, hi * 2
    while hi - lo > max(1, lo // 10):  # within 10%
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if run(mid) else (lo, mid)
    best = max((t for t in trials if t["ok"]), key=lambda t: t["robots"], default=None)
    return MaxRobots(backend, socket, lo, best, trials)


def run_bench(
    backends: list[str],
    seconds: float = 3.0,
    log: Any = None,
    answer: bool = True,
    sockets: tuple[str, ...] = ("own",),
) -> RobotsResult:
    """Each backend's most robots, with a socket a robot (own) and with one for the group (shared)."""
    baseline = {"backend": "kinematic", **trial("kinematic", 1, seconds, answer)}
    if log:
        log(baseline)
    starts = {
        ("kinematic", "own"): 32,
        ("mujoco", "own"): 16,
        ("kinematic", "shared"): 128,
        ("mujoco", "shared"): 16,
    }
    out = RobotsResult(baseline, answer)
    for b in backends:
        for sock in sockets:
            key = b if sock == "own" else f"{b}_shared"
            setattr(out, key, max_robots(b, starts[b, sock], seconds, log, answer, sock))
    return out


def format_trial(r: dict[str, Any]) -> str:
    verdict = "ok  " if r["ok"] else "FAIL"
    return (
        f"{r.get('backend', ''):>10} {r.get('socket', 'own'):>6} {int(r['robots']):>4} robots: {verdict} "
        f"late {100 * r['late_fraction']:.3f}%  "
        f"sent {int(r.get('status_sent', 0)):,}/{int(r['expected']):,}  "
        f"commands {int(r.get('commands', 0)):,}  missed ticks {int(r.get('missed_ticks', 0))}  "
        f"tick lateness p50/p99 {r.get('lateness_p50_us', float('nan')):.0f}/"
        f"{r.get('lateness_p99_us', float('nan')):.0f} us  cpu {100 * r.get('cpu', 0):.0f}%"
    )


def format_result(result: RobotsResult) -> str:
    who = "answered by a reflector on the other core" if result.answered else "status only"
    lines = [f"robots at 500 Hz status on one core with < 0.1% late sends ({who}):"]
    lines.append(f"  baseline, 1 robot (the machine's own stalls): {format_trial(result.baseline).strip()}")
    for b, r in result.backends().items():
        best = f"  [{format_trial(r.best).strip()}]" if r.best else ""
        name = b.replace("_shared", ", one shared socket") if b.endswith("_shared") else f"{b}, a socket each"
        lines.append(f"  {name}: {r.max_robots} robots{best}")
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=["kinematic", "mujoco", "all"], default="all")
    p.add_argument("--seconds", type=float, default=3.0, help="length of each trial (default 3)")
    p.add_argument(
        "--status-only", action="store_true", help="nobody answers the status (no command traffic)"
    )
    p.add_argument(
        "--socket",
        choices=["own", "shared", "both"],
        default="both",
        help="a UDP socket per robot (a real arm's), one for the group (fleets: [robot_defaults] socket), "
        "or both (default)",
    )


def _main(args: argparse.Namespace) -> Figures:
    backends = ["kinematic", "mujoco"] if args.backend == "all" else [args.backend]
    sockets = ("own", "shared") if args.socket == "both" else (args.socket,)
    result = run_bench(
        backends,
        args.seconds,
        log=lambda trial: log(format_trial(trial)),
        answer=not args.status_only,
        sockets=sockets,
    )
    return Figures(result, format_result(result))


register(
    Bench(
        "robots",
        "the most robots one core runs at 500 Hz status with < 0.1% late sends, per backend",
        _arguments,
        _main,
    )
)
