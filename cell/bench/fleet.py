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

--churn adds the paper's continuous table management (Sec. 7.4, Fig. 12) beside the arms: 3.4K TPs
no arm follows loaded first, then each second 1.6K more inserted and, half a second on, the 1.6K
oldest removed (about 10K joint entries: the paper's "+1.6K / -10K"), through the same data plane
and its one update at a time, as a controller using the tables as a playback buffer would.  The
arms' status-to-command time comes as a time series (each GroupTruth: the answers since the last).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import resource
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell import sched
from cell.bench.registry import Bench, Failed, Figures, log, register
from cell.bench.robots import late_statuses
from cell.bus import Bus, BusTimeout
from cell.cellproc import robots_heard, running_cell
from cell.config import DATAPLANE_BACKENDS, load_config
from cell.controller.controller import Controller, MotionStopped, Segment
from cell.controller.motion import NotAtGoal
from cell.dataplane.tables import TPBatch
from cell.launcher import fetch_status
from cell.robot.arm import arm_model
from cell.v1 import robot_pb2

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
TRUTH_HZ = 250  # a sample every second status period: every TP of a motion started on a window start
LATE_AIM = 0.005  # late statuses, fraction (the search's bound)
PATH_AIM_MM = 0.1  # median path error (the search's bound)
DWELL_S = 1.0  # an arm rests up to this long between motions (uniformly: a pick, a place)
CHURN_PRELOAD, CHURN_TPS = 3_400, 1_600  # Fig. 12: TPs loaded first, then in and out each second
CHURN_ID0 = 3_000_000_000  # the churn's TP ids: far above any the controller takes in a run
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
    unanswered: int = 0  # arms whose controller's read of the data plane went unanswered (2 s): they stop
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
    churn: Churn | None = None  # --churn: the table management beside the arms
    series: Series | None = None  # the latency and the loaded TPs over the run

    def figures(self, max_robots: int | None = None) -> dict[str, Any]:
        out = {k: v for k, v in asdict(self).items() if k not in ("churn", "series")}
        out["max_robots"] = max_robots if max_robots is not None else (self.robots if self.ok else 0)
        if self.churn is not None:
            out["churn_update_ms_mean"] = self.churn.update_ms_mean
            out["churn_updates"] = len(self.churn.phases)
        return out


@dataclass
class FleetResult:
    """What `cell bench fleet` hands on: a run, and with --search the largest fleet that passed (the
    JSON line's max_robots; without it, the run's own robots if it passed)."""

    run: FleetRun
    max_robots: int | None = None

    def to_json(self) -> dict[str, Any]:
        return self.run.figures(self.max_robots)


@dataclass
class Series:
    """Over the run (seconds from its start): the arms' status-to-command time, each sample the
    answers of one GroupTruth interval (mean and max, us), and the TPs in the tables after each update."""

    t_s: np.ndarray
    latency_us_mean: np.ndarray
    latency_us_max: np.ndarray
    loaded_t_s: np.ndarray
    loaded: np.ndarray


@dataclass
class Churn:
    """--churn's updates: each phase (start s, end s, "insert" or "remove") and its time."""

    phases: list[tuple[float, float, str]] = field(default_factory=list)

    @property
    def update_ms_mean(self) -> float:
        return float(np.mean([1e3 * (b - a) for a, b, _ in self.phases])) if self.phases else float("nan")


class _TimedUpdates:
    """The controller's table updates timed (t_upd, as the controller sees it: request to reply, the
    bus both ways): its data-plane client's `update`, which all its parts share, wrapped in place.
    `untimed` still sends an update as it was (the churn's, which is not the controller's)."""

    def __init__(self, dp: Any, loaded: list[tuple[float, int]]) -> None:
        self.untimed = dp.update
        self.ms: list[float] = []
        self.loaded = loaded  # (monotonic s, TPs in the tables after the update)
        dp.update = self.update

    async def update(self, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        reply = await self.untimed(*args, **kwargs)
        self.ms.append((time.perf_counter() - t0) * 1e3)
        self.loaded.append((time.monotonic(), int(reply.loaded)))
        return reply


async def _on_a_par() -> None:
    """The controller (the paper's is another machine) on a par with the robots' Python, not under it:
    this thread at their nice while the fleet runs (not the cell it started), its own nice again after."""
    tid = threading.get_native_id()
    was = os.getpriority(os.PRIO_PROCESS, tid)
    try:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, sched.RT_NICE)
        await asyncio.Future()  # (until the run ends)
    finally:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, was)


class _Truth:
    """The group's ground truth as it arrives: times and every arm's joints (fleet/<name>)."""

    def __init__(self) -> None:
        self.t: list[int] = []
        self.q: list[np.ndarray] = []
        self.columns: dict[int, int] = {}
        self.answers: list[tuple[int, float, float]] = []  # each message's (answers, mean us, max us)

    async def run(self, bus: Bus) -> None:
        sub = await bus.subscribe("fleet/")
        async for env in sub:
            m = env.decode(robot_pb2.GroupTruth)
            if not self.columns:
                self.columns = {int(r): i for i, r in enumerate(m.robot_id)}
            self.t.append(int(m.t_ns))
            self.q.append(np.array(m.q).reshape(-1, m.joints))
            self.answers.append((m.answers, m.answer_us_mean, m.answer_us_max))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.t, np.int64), np.stack(self.q)


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


async def measure(
    n: int, seconds: float, backend: str = "auto", quiet: bool = False, churn: bool = False
) -> FleetRun:
    say = (lambda _m: None) if quiet else log
    robots: list[dict[str, Any]] = [
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
    if backend == "auto":  # (named by what auto chooses here, as cell config show says)
        backend = load_config(None).dataplane.chosen()[0]
    elif not DATAPLANE_BACKENDS[backend].in_kernel:
        overrides["dataplane"] = {"backend": backend}
    if DATAPLANE_BACKENDS[backend].in_kernel:
        from cell.bench.xdpnet import xdp_dataplane, xdp_switch

        overrides["dataplane"] = xdp_dataplane(xdp_switch(cpu=0, tag="cbf"))
        # the kernel runs the packet path (on the robots' core, as it sends): the data plane's process
        # is only its control plane, so it leaves the robots' core to them
        groups = [asdict(g) for g in load_config(None).services.groups]
        for g in groups:
            if g["name"] == "dataplane":
                g["cpus"] = [0]
        overrides["services"]["groups"] = groups
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
        contextlib.AsyncExitStack() as stack,
    ):
        background = [tg.create_task(truth.run(bus)), tg.create_task(_on_a_par())]
        stack.callback(lambda: [task.cancel() for task in background])  # (they run until told)
        await robots_heard(ctl, set(range(1, n + 1)), timeout=30.0)
        loaded: list[tuple[float, int]] = []
        timed = _TimedUpdates(ctl.dp, loaded)  # (its parts' updates; its reads go through ctl.link)
        try:
            for p in pairs:
                await ctl.merge(p)
        except BusTimeout:  # (a host too busy to set the fleet up: a failed run, counted, not a crash)
            run.unanswered += 1
            return run
        if churn:
            run.churn = Churn()
            owners = np.array([int(x[1:]) for x in singles])
            reply = await timed.untimed(insert=dealt(owners, 0, CHURN_PRELOAD))
            loaded.append((time.monotonic(), int(reply.loaded)))
            background.append(tg.create_task(_churn(timed.untimed, owners, run.churn, loaded)))
        procs, c0 = await _snapshot(config)
        cpu0 = {k: sched.process_cpu_seconds(pid) for k, pid in procs.items()}
        me0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.monotonic()
        deadline = t0 + seconds
        say(
            f"{n} arms ({len(pairs)} merged pairs) for {seconds:g} s, data plane {backend}"
            + (f", table churn +{CHURN_TPS} / -{CHURN_TPS} TPs a second" if churn else "")
        )

        async def drive(entity: list[str], seed: int) -> None:
            rng = np.random.default_rng(seed)
            await asyncio.sleep(rng.uniform(0.0, 1.0))  # staggered starts
            start = np.tile(Q0, len(entity))
            here = start
            while time.monotonic() < deadline - 1.0:
                # (a walk kept within 1.2 rad of the start: unbounded, some arms walked into a joint
                # limit over a long run, and stood short of goals they could not reach)
                goal = np.clip(here + rng.uniform(-0.5, 0.5, here.size), start - 1.2, start + 1.2)
                try:
                    await ctl.move_joints(entity[0], goal, speed=float(rng.uniform(0.4, 0.9)))
                except (MotionStopped, NotAtGoal):
                    run.stopped += 1
                    return
                except BusTimeout:  # (a host too busy for the controller: counted, the run goes on)
                    run.unanswered += 1
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
        cpu1 = {k: sched.process_cpu_seconds(pid) for k, pid in procs.items()}
        _, c1 = await _snapshot(config)
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
    run.series = _series(truth, loaded, t0)
    if run.churn is not None:
        run.churn.phases = [(a - t0, b - t0, kind) for a, b, kind in run.churn.phases]
    run.ok = (
        run.late_status_pct < 100 * LATE_AIM
        and run.path_error_mm_median <= PATH_AIM_MM
        and not run.unanswered
    )
    return run


def dealt(owners: np.ndarray, first: int, n: int, id0: int = CHURN_ID0) -> TPBatch:
    """Parked TPs first..first+n (ids from id0 on), dealt round the owners."""
    k = np.arange(first, first + n)
    return TPBatch.parked(owners[k % owners.size], id0 + k)


async def _churn(update: Any, owners: np.ndarray, churn: Churn, loaded: list[tuple[float, int]]) -> None:
    """Each second 1,600 TPs in, and half a second on the 1,600 oldest out (the preload's first),
    until cancelled; each phase timed, the tables' count after it kept."""
    oldest, newest = 0, CHURN_PRELOAD
    due = time.monotonic()
    while True:
        for kind in ("insert", "remove"):
            due += 0.5
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            a = time.monotonic()
            if kind == "insert":
                reply = await update(insert=dealt(owners, newest, CHURN_TPS))
                newest += CHURN_TPS
            else:
                gone = dealt(owners, oldest, CHURN_TPS)
                reply = await update(remove=gone.keys)
                oldest += CHURN_TPS
            b = time.monotonic()
            churn.phases.append((a, b, kind))
            loaded.append((b, int(reply.loaded)))


def _series(truth: _Truth, loaded: list[tuple[float, int]], t0: float) -> Series:
    t = np.array(truth.t, np.float64) / 1e9 - t0
    a = np.array(truth.answers, np.float64).reshape(-1, 3)
    some = a[:, 0] > 0
    lt = np.array(loaded, np.float64).reshape(-1, 2)
    return Series(t[some], a[some, 1], a[some, 2], lt[:, 0] - t0, lt[:, 1].astype(np.int64))


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
    """The largest N within the bounds: N doubles from `start` until a run fails, then three bisections
    (to an eighth of the last doubling: 800 -> 1600 is found to within 100).
    A failed run is tried once more before N counts as too many (a VM's stall of a few ms makes one
    run's late statuses, not the fleet's size)."""
    runs: list[FleetRun] = []

    def passes(n: int) -> bool:
        for _ in range(2):
            r = asyncio.run(measure(n, seconds, backend, quiet=True))
            runs.append(r)
            log(format_run(r))
            if r.ok:
                return True
        return False

    ok, n = 0, start
    while n <= limit and passes(n):
        ok, n = n, n * 2
    bad = n
    for _ in range(3):
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
        + (f" ({r.unanswered} arms' reads of the data plane unanswered)" if r.unanswered else "")
    )


def format_result(result: FleetResult) -> str:
    r, max_robots = result.run, result.max_robots
    cpu = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r.cpu.items())
    lines = [
        format_run(r),
        f"  tool error at {r.tps_scored:,} TPs; stop error {r.stop_error_rad_max:.1e} rad "
        f"(paper: {PAPER['path']})",
        f"  table updates {r.updates_per_s:.0f}/s, t_upd (request to reply) p50 {r.t_upd_ms:.1f} ms, "
        f"p99 {r.t_upd_ms_p99:.1f} ms",
        f"  CPU (share of a core): {cpu}",
    ]
    if r.churn is not None:
        lines.insert(
            3,
            f"  table churn beside them: {len(r.churn.phases)} updates of {CHURN_TPS:,} TPs, "
            f"{r.churn.update_ms_mean:.1f} ms each on average (paper: +1.6K / -10K entries a second, "
            "no effect on latency)",
        )
    if max_robots is not None:
        lines.append(
            f"largest fleet within < {100 * LATE_AIM:g}% late statuses and a median path error <= "
            f"{PATH_AIM_MM} mm: {max_robots} arms (paper: {PAPER['robots']}; {PAPER['x86']})"
        )
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robots", type=int, default=100, help="arms in the fleet (default 100)")
    p.add_argument("--seconds", type=float, default=10.0, help="how long they move (default 10)")
    p.add_argument(
        "--backend",
        choices=["auto", "numpy", "native", "xdp"],
        default="auto",
        help="the data plane (default: the cell's [dataplane] backend; xdp needs root)",
    )
    p.add_argument("--search", action="store_true", help="find the largest fleet within the bounds")
    p.add_argument(
        "--churn",
        action="store_true",
        help="table churn beside the arms: 1.6K TPs in and out a second (Fig. 12)",
    )


def _main(args: argparse.Namespace) -> Figures:
    if args.robots < 1 or args.seconds < 2:
        why = "--robots >= 1 and --seconds >= 2"
        return Figures(Failed(why), why, 2)
    if args.search:
        best, runs = search(args.seconds, args.backend)
        top = max((r for r in runs if r.ok), key=lambda r: r.robots, default=runs[-1])
        result = FleetResult(top, best)
        return Figures(result, format_result(result))
    with contextlib.suppress(KeyboardInterrupt):
        result = FleetResult(asyncio.run(measure(args.robots, args.seconds, args.backend, churn=args.churn)))
        return Figures(result, format_result(result))
    return Figures(Failed("interrupted"), "", 130)


register(
    Bench(
        "fleet",
        "N arms on one socket, each following its own motions through the data plane: late statuses, "
        "latency, path error per arm, t_upd, CPU; --search for the largest fleet (NSDI'22 Sec. 7.5)",
        _arguments,
        _main,
    )
)
