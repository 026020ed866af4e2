"""`cell bench fleet`: the NSDI'22 evaluation at the paper's scale (Sec. 7.5, App. B).

N kinematic UR5e arms of one group on one shared socket (`socket = "shared"`: one GSO run of
statuses a tick) are each driven through the data plane by the controller in this process: joint
moves to goals of their own (other shapes, other speeds), starts staggered over the first second, a
tenth of the arms merged into pairs that move as one entity, the controller loading and removing
their TPs episode by episode as it does for two arms.  The arms' ground truth comes one message a
tick for the whole group (GroupTruth on fleet/<name>, at 250 Hz: every TP of a motion started on a
window start falls on one of its samples).

Figures: late statuses (the fleet's sends more than a period late, and whole missed ticks), the
status-to-command time as the arms see it (kernel stamps, cell.robot.emulator's `answers`), each
arm's tool error at its TPs (the median over arms of each arm's median, the p99 over arms of each
arm's maximum, the worst arm), the stop error, the controller's table updates (a second, and t_upd:
request to reply), and the CPU each process used.  --search finds the largest N that keeps late
statuses < 0.5 % and the median path error <= 0.1 mm (each trial a fresh cell).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import resource
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell.bench.cellproc import robots_heard, running_cell
from cell.bench.registry import Bench, Figures, log, register
from cell.bench.robots import late_statuses
from cell.bus import Bus
from cell.controller.controller import Controller, MotionStopped, Segment
from cell.controller.schedule import NotAtGoal
from cell.launcher import fetch_status
from cell.robot.arm import arm_model
from cell.v1 import robot_pb2

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
TRUTH_HZ = 250  # a sample every second status period: every TP of a motion started on a window start
LATE_AIM = 0.005  # late statuses, fraction (the search's bound)
PATH_AIM_MM = 0.1  # median path error (the search's bound)
DWELL_S = 1.0  # an arm rests up to this long between motions (uniformly: a pick, a place)
PAPER = {
    "robots": "500 (one Tofino, t_upd-bound; Sec. 7.5), 1000 at shorter episodes",
    "x86": "45 arms on a 12-core server (App. B, the ROS driver)",
    "path": "3.2 / 2.23 mm max / median in-network (Sec. 7.2)",
}


@dataclass
class FleetRun:
    """One run of N arms (see the module's docstring)."""

    robots: int
    backend: str
    seconds: float
    motions: int = 0  # motions that ran to their end
    stopped: int = 0  # motions that did not (a loss, a watchdog stop): each arm's error is then its own
    late_status_pct: float = 0.0
    latency_us_p50: float = float("nan")
    latency_us_p99: float = float("nan")
    path_error_mm_median: float = float("nan")  # median over arms of each arm's median at its TPs
    path_error_mm_p99: float = float("nan")  # p99 over arms of each arm's maximum
    path_error_mm_max: float = float("nan")
    worst_arm: str = ""
    stop_error_rad_max: float = float("nan")
    tps_scored: int = 0
    updates_per_s: float = 0.0
    t_upd_ms: float = float("nan")  # an update's request to reply, median
    t_upd_ms_p99: float = float("nan")
    cpu: dict[str, float] = field(default_factory=dict)  # share of a core, per process
    ok: bool = False  # late statuses and the median path error within the search's bounds

    def figures(self, max_robots: int | None = None) -> dict[str, Any]:
        out = asdict(self)
        out["max_robots"] = max_robots if max_robots is not None else (self.robots if self.ok else 0)
        return out


class _TimedUpdates:
    """The controller's data-plane client with each table update timed (t_upd, as the controller
    sees it: request to reply, the bus both ways)."""

    def __init__(self, dp: Any) -> None:
        self.dp = dp
        self.ms: list[float] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.dp, name)

    async def update(self, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        reply = await self.dp.update(*args, **kwargs)
        self.ms.append((time.perf_counter() - t0) * 1e3)
        return reply


class _Truth:
    """The group's ground truth as it arrives: times and every arm's joints (fleet/<name>)."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.q: list[np.ndarray] = []
        self.columns: dict[int, int] = {}

    async def run(self, bus: Bus) -> None:
        sub = await bus.subscribe("fleet/")
        async for env in sub:
            m = env.decode(robot_pb2.GroupTruth)
            if not self.columns:
                self.columns = {int(r): i for i, r in enumerate(m.robot_id)}
            self.t.append(int(m.t_ns))
            self.q.append(np.array(m.q).reshape(-1, m.joints))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.t, np.int64), np.stack(self.q)


def _cpu_s(pid: int) -> float:
    """A process's user + system CPU seconds so far (/proc)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except OSError:
        return float("nan")


async def _snapshot(config: Any) -> tuple[dict[str, int], dict[str, float]]:
    """The cell's processes (name -> pid; services sharing a process under one name) and the robots
    service's counters, from one status."""
    st = await fetch_status(config)
    by_pid: dict[int, list[str]] = {}
    for s in st.services:
        if s.last.pid:
            by_pid.setdefault(s.last.pid, []).append(s.name)
    robots = dict(next(s for s in st.services if s.name == "robots").last.counters)
    return {"+".join(names): pid for pid, names in by_pid.items()}, robots


async def measure(n: int, seconds: float, backend: str = "numpy", quiet: bool = False) -> FleetRun:
    say = (lambda _m: None) if quiet else log
    robots = [
        {
            "id": i,
            "name": f"f{i}",
            "skill_port": 20000 + i,
            "backend": "kinematic",
            "socket": "shared",
            "truth_hz": TRUTH_HZ,
        }
        for i in range(1, n + 1)
    ]
    overrides: dict[str, Any] = {"robots": robots, "services": {"run": ["bus", "dataplane", "robots"]}}
    if backend == "xdp":
        from cell.bench.dataplane import xdp_dataplane, xdp_switch

        overrides["dataplane"] = xdp_dataplane(xdp_switch(tag="cbf"))
    names = [r["name"] for r in robots]
    pairs = [names[i : i + 2] for i in range(0, n // 10 * 2, 2)] if n >= 10 else []  # a tenth, merged
    paired = {x for p in pairs for x in p}
    singles = [x for x in names if x not in paired]
    run = FleetRun(n, backend, seconds)
    segments: list[tuple[list[str], Segment]] = []  # (the robots it drives, in its joint order)
    truth = _Truth()
    async with (
        running_cell(overrides, quiet=True) as config,
        Bus.connect(config.bus, "bench-fleet") as bus,
        Controller(bus, config) as ctl,
        asyncio.TaskGroup() as tg,
    ):
        watcher = tg.create_task(truth.run(bus))
        await robots_heard(ctl, set(range(1, n + 1)), timeout=30.0)
        timed = _TimedUpdates(ctl.dp)
        ctl.dp = timed  # type: ignore[assignment]  (the engine's updates; its reads go through ctl.link)
        for p in pairs:
            await ctl.merge(p)
        procs, c0 = await _snapshot(config)
        cpu0 = {k: _cpu_s(pid) for k, pid in procs.items()}
        me0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.monotonic()
        deadline = t0 + seconds
        say(f"{n} arms ({len(pairs)} merged pairs) for {seconds:g} s, data plane {backend}")

        async def drive(entity: list[str], seed: int) -> None:
            rng = np.random.default_rng(seed)
            await asyncio.sleep(rng.uniform(0.0, 1.0))  # staggered starts
            here = np.tile(Q0, len(entity))
            while time.monotonic() < deadline - 1.0:
                goal = here + rng.uniform(-0.5, 0.5, here.size)
                try:
                    await ctl.move_joints(entity[0], goal, speed=float(rng.uniform(0.4, 0.9)))
                except (MotionStopped, NotAtGoal):
                    run.stopped += 1
                    return
                seg = ctl.track(entity[0]).segment
                if seg is not None:
                    segments.append((entity, seg))
                run.motions += 1
                here = goal
                await asyncio.sleep(rng.uniform(0.0, DWELL_S))  # (a pick, a place: the arm dwells)

        async with asyncio.TaskGroup() as arms:
            for k, entity in enumerate([*pairs, *([x] for x in singles)]):
                arms.create_task(drive(entity, k))
        spent = time.monotonic() - t0
        await asyncio.sleep(1.0)  # the last holds: the stop error is read 1 s on
        me1 = resource.getrusage(resource.RUSAGE_SELF)
        cpu1 = {k: _cpu_s(pid) for k, pid in procs.items()}
        _, c1 = await _snapshot(config)
        watcher.cancel()
    run.seconds = round(spent, 1)
    run.cpu = {k: round((cpu1[k] - cpu0[k]) / spent, 2) for k in procs}
    run.cpu["controller (this process)"] = round(
        (me1.ru_utime + me1.ru_stime - me0.ru_utime - me0.ru_stime) / spent, 2
    )
    grew = {k: c1.get(k, 0) - c0.get(k, 0) for k in ("late_sends", "missed_ticks")}
    late, expected = late_statuses(grew["late_sends"], grew["missed_ticks"], n, spent)
    run.late_status_pct = 100 * late / expected
    run.latency_us_p50, run.latency_us_p99 = c1.get("answer_p50_us", np.nan), c1.get("answer_p99_us", np.nan)
    if timed.ms:
        run.updates_per_s = len(timed.ms) / spent
        run.t_upd_ms, run.t_upd_ms_p99 = (float(np.percentile(timed.ms, p)) for p in (50, 99))
    _score(run, truth, segments)
    run.ok = run.late_status_pct < 100 * LATE_AIM and run.path_error_mm_median <= PATH_AIM_MM
    return run


def _score(run: FleetRun, truth: _Truth, segments: list[tuple[list[str], Segment]]) -> None:
    """Each arm's tool error at the TPs of its motions (the truth at each TP's time, against the TP)."""
    if not truth.t or not segments:
        return
    t, q = truth.arrays()
    col = {f"f{r}": c for r, c in truth.columns.items()}
    arm = arm_model("ur5e")
    per_arm: dict[str, list[float]] = {}
    for entity, seg in segments:
        t_tp = np.array([seg.t_ns(k) for k in range(len(seg.sections))])
        inside = (t_tp >= t[0]) & (t_tp <= t[-1])
        for j, name in enumerate(entity):
            plan = seg.sections.q[:, 6 * j : 6 * j + 6][inside]
            real = np.stack([np.interp(t_tp[inside], t, q[:, col[name], i]) for i in range(6)], axis=1)
            errs = [
                float(np.linalg.norm(arm.fk(a)[0] - arm.fk(b)[0])) * 1e3
                for a, b in zip(real, plan, strict=True)
            ]
            per_arm.setdefault(name, []).extend(errs)
    if not per_arm:
        return
    medians = np.array([np.median(v) for v in per_arm.values()])
    maxima = {k: max(v) for k, v in per_arm.items()}
    run.tps_scored = sum(len(v) for v in per_arm.values())
    run.path_error_mm_median = float(np.median(medians))
    run.path_error_mm_p99 = float(np.percentile(list(maxima.values()), 99))
    run.worst_arm, run.path_error_mm_max = max(maxima.items(), key=lambda kv: kv[1])
    # the stop error: each arm's last goal (its last segment's end) against where it stands (the
    # truth's last sample)
    last: dict[str, tuple[np.ndarray, int]] = {}
    for entity, seg in segments:
        for j, name in enumerate(entity):
            if seg.end_ns >= last.get(name, (None, -1))[1]:
                last[name] = (seg.sections.q[-1, 6 * j : 6 * j + 6], seg.end_ns)
    errs = [float(np.abs(q[-1, col[name]] - g).max()) for name, (g, end) in last.items() if end < t[-1]]
    run.stop_error_rad_max = max(errs) if errs else float("nan")


def search(seconds: float, backend: str, start: int = 50, limit: int = 2000) -> tuple[int, list[FleetRun]]:
    """The largest N within the bounds: N doubles from `start` until a run fails, then two bisections."""
    runs: list[FleetRun] = []

    def passes(n: int) -> bool:
        r = asyncio.run(measure(n, seconds, backend, quiet=True))
        runs.append(r)
        log(format_run(r))
        return r.ok

    ok, n = 0, start
    while n <= limit and passes(n):
        ok, n = n, n * 2
    bad = n
    for _ in range(2):
        mid = (ok + bad) // 2
        if mid <= ok or mid > limit:
            break
        if passes(mid):
            ok = mid
        else:
            bad = mid
    return ok, runs


def format_run(r: FleetRun) -> str:
    verdict = "ok  " if r.ok else "FAIL"
    return (
        f"{r.robots:>5} arms ({r.backend}): {verdict} late statuses {r.late_status_pct:.3f}%  "
        f"status->command p50/p99 {r.latency_us_p50:.0f}/{r.latency_us_p99:.0f} us  path error at TPs "
        f"median {r.path_error_mm_median:.3f} mm, p99 of maxima {r.path_error_mm_p99:.3f} mm "
        f"(worst {r.worst_arm} {r.path_error_mm_max:.3f} mm)  {r.motions} motions"
        + (f" ({r.stopped} stopped)" if r.stopped else "")
    )


def format_result(r: FleetRun, max_robots: int | None) -> str:
    cpu = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r.cpu.items())
    lines = [
        format_run(r),
        f"  tool error at {r.tps_scored:,} TPs; stop error {r.stop_error_rad_max:.1e} rad "
        f"(paper: {PAPER['path']})",
        f"  table updates {r.updates_per_s:.0f}/s, t_upd (request to reply) p50 {r.t_upd_ms:.1f} ms, "
        f"p99 {r.t_upd_ms_p99:.1f} ms",
        f"  CPU (share of a core): {cpu}",
    ]
    if max_robots is not None:
        lines.append(
            f"largest fleet within < {100 * LATE_AIM:g}% late statuses and a median path error <= "
            f"{PATH_AIM_MM} mm: {max_robots} arms (paper: {PAPER['robots']}; {PAPER['x86']})"
        )
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robots", type=int, default=100, help="arms in the fleet (default 100)")
    p.add_argument("--seconds", type=float, default=10.0, help="how long they move (default 10)")
    p.add_argument("--backend", choices=["numpy", "xdp"], default="numpy", help="the data plane (xdp: root)")
    p.add_argument("--search", action="store_true", help="find the largest fleet within the bounds")


def _main(args: argparse.Namespace) -> Figures:
    if args.robots < 1 or args.seconds < 2:
        return Figures({"error": "--robots >= 1 and --seconds >= 2"}, "--robots >= 1 and --seconds >= 2", 2)
    if args.search:
        best, runs = search(args.seconds, args.backend)
        top = max((r for r in runs if r.ok), key=lambda r: r.robots, default=runs[-1])
        return Figures(top.figures(best), format_result(top, best))
    with contextlib.suppress(KeyboardInterrupt):
        r = asyncio.run(measure(args.robots, args.seconds, args.backend))
        return Figures(r.figures(), format_result(r, None))
    return Figures({"error": "interrupted"}, "", 130)


register(
    Bench(
        "fleet",
        "N arms on one socket, each following its own motions through the data plane: late statuses, "
        "latency, path error per arm, t_upd, CPU; --search for the largest fleet (NSDI'22 Sec. 7.5)",
        _arguments,
        _main,
    )
)
