"""`cell bench paper`'s experiments on scale (Sec. 7.5, Apps. A-B): table capacity, churn with the
arms moving (Fig. 12), resources (Fig. 13a-b), arms against episodes (Fig. 13c-d), x86 drivers."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cell.bench.paper.page import Log, Section, plt_, save


def scaling(quick: bool, out: Path, log: Log) -> list[Section]:
    from cell.config import load_config
    from cell.dataplane.tables import Tables, TPBatch

    cfg = load_config(None)
    cap, episode, rate = cfg.dataplane.capacity, cfg.controller.episode, cfg.controller.tp_rate_hz
    # at most 3 episodes of each robot in the tables (the one running, the next, the one leaving)
    per_robot = 3 * episode
    fleet = cap // per_robot
    sizes = (10, 100, 1000, 5000) if quick else (10, 100, 1000, 5000, 20000)
    t_upd = {}
    for n in sizes:
        t = Tables(capacity=cap)
        t.add_robot(1)
        ids = np.arange(n)
        batch = TPBatch(
            np.full(n, 1), ids, ids, np.full(n, 0.1), np.full(n, 6), np.zeros((n, 6)), np.zeros((n, 6))
        )
        reps = 5
        t0 = time.perf_counter_ns()
        for _ in range(reps):
            t.update(insert=batch)
            t.update(remove=[(1, int(i)) for i in ids])
        t_upd[n] = (time.perf_counter_ns() - t0) / reps / 2 / 1e6
        log(f"t_upd for {n} TPs: {t_upd[n]:.2f} ms")
    plt = plt_()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.2))
    robots = np.array([1, 10, 100, 1000, 10000])
    for ep_s, style in ((2.0, "-"), (10.0, "--")):
        for hz in (10, 125):
            a1.loglog(robots, robots * ep_s * hz, style, label=f"{ep_s:.0f} s episodes, {hz} TP/s")
    a1.axhline(cap, color="k", lw=0.8)
    a1.text(1, cap * 1.2, f"capacity {cap:,}")
    a1.set_xlabel("robots")
    a1.set_ylabel("TPs in the tables")
    a1.legend(fontsize=7)
    a2.loglog(list(t_upd), list(t_upd.values()), "o-")
    a2.set_xlabel("TPs in one update")
    a2.set_ylabel("t_upd (ms)")
    return [
        Section(
            "scaling",
            "Scaling",
            "Appendix A, Fig. 13",
            [
                ("table capacity", "50K TPs (the paper's switch)", f"{cap:,} TPs"),
                (
                    "largest fleet at the default (episodes of "
                    f"{episode} TPs at {rate:g} TP/s, 3 in the tables)",
                    "-",
                    f"{fleet:,} robots",
                ),
            ]
            + [(f"t_upd, {n:,} TPs", "-", f"{v:.2f} ms") for n, v in t_upd.items()],
            save(fig, out, "scaling.png"),
            "t_upd: inserting a batch into the Tables and deleting it again, in process (the bus adds "
            "its own time: see churn).",
            {"capacity": cap, "largest_fleet": fleet} | {f"t_upd_ms_{n}": v for n, v in t_upd.items()},
            caption="Left: TPs the tables must hold against the fleet size, per episode length and TP "
            "rate, with the capacity.  Right: the time to insert and delete one batch of TPs.",
            headline=("50K TPs, 500-1,000 robots", f"{cap:,} TPs, {fleet:,} robots"),
            verdict="yes" if fleet >= 500 else "scaled",
        )
    ]


def churn(quick: bool, out: Path, log: Log) -> list[Section]:
    """Fig. 12 with the arms moving: the fleet bench twice, the same arms and motions, without and
    with the paper's table churn beside them."""
    from cell.bench import fleet

    n, seconds = (40, 6.0) if quick else (150, 12.0)
    quiet = asyncio.run(fleet.measure(n, seconds, quiet=True))
    log(fleet.format_run(quiet))
    busy = asyncio.run(fleet.measure(n, seconds, quiet=True, churn=True))
    log(fleet.format_run(busy))
    assert busy.churn is not None and busy.series is not None and quiet.series is not None
    plt = plt_()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    s = busy.series
    top.step(s.loaded_t_s, s.loaded / 1e3, where="post", color="k", lw=1)
    for a, b, kind in busy.churn.phases:
        top.axvspan(a, max(b, a + 0.02), color="tab:blue" if kind == "insert" else "tab:red", alpha=0.3)
    top.set_ylabel("TPs loaded (K)")
    top.set_title("insertion (blue) and removal (red) phases", fontsize=8)
    window = max(1, round(0.25 / np.median(np.diff(s.t_s)))) if s.t_s.size > 2 else 1
    for run, colour, label in ((quiet, "tab:gray", "no churn"), (busy, "tab:green", "churn")):
        r = run.series
        assert r is not None
        if run is busy:
            bottom.plot(r.t_s, r.latency_us_mean, ".", ms=1, color=colour, alpha=0.4)
        if r.t_s.size >= window:
            avg = np.convolve(r.latency_us_mean, np.ones(window) / window, mode="valid")
            bottom.plot(r.t_s[window - 1 :], avg, color=colour, label=f"{label}, moving average")
    bottom.set_xlabel("time (s)")
    bottom.set_ylabel("status to command (us)")
    bottom.legend(fontsize=7)
    ms = [1e3 * (b - a) for a, b, _ in busy.churn.phases]
    lat = {"quiet": float(np.mean(quiet.series.latency_us_mean)), "churn": float(np.mean(s.latency_us_mean))}
    held = lat["churn"] <= 1.5 * lat["quiet"] and busy.path_error_mm_median <= 2 * max(
        quiet.path_error_mm_median, 0.01
    )
    return [
        Section(
            "churn",
            "Table churn with the arms moving",
            "Sec. 7.4, Fig. 12",
            [
                (
                    "TPs loaded first; then in / out a second",
                    "3.4K; +1.6K / -10K entries",
                    f"{fleet.CHURN_PRELOAD / 1e3:.1f}K; +{fleet.CHURN_TPS / 1e3:.1f}K / "
                    f"-{fleet.CHURN_TPS / 1e3:.1f}K TPs (-{6 * fleet.CHURN_TPS / 1e3:.1f}K joint entries)",
                ),
                (
                    "time of one churn update (1.6K TPs)",
                    "-",
                    f"{np.mean(ms):.1f} ms mean, {max(ms):.1f} ms max",
                ),
                (
                    "status to command, mean: without / with churn",
                    "no effect",
                    f"{lat['quiet']:.0f} / {lat['churn']:.0f} us",
                ),
                (
                    "status to command p99: without / with churn",
                    "-",
                    f"{quiet.latency_us_p99:.0f} / {busy.latency_us_p99:.0f} us",
                ),
                (
                    "tool path error at TPs, median: without / with churn",
                    "-",
                    f"{quiet.path_error_mm_median:.3f} / {busy.path_error_mm_median:.3f} mm",
                ),
                (
                    "tool path error, p99 of each arm's max: without / with churn",
                    "-",
                    f"{quiet.path_error_mm_p99:.3f} / {busy.path_error_mm_p99:.3f} mm",
                ),
                (
                    "the controller's own updates: t_upd p50 without / with churn",
                    "-",
                    f"{quiet.t_upd_ms:.1f} / {busy.t_upd_ms:.1f} ms",
                ),
            ],
            save(fig, out, "churn.png"),
            f"{n} kinematic arms follow their own motions through the data plane (cell bench fleet) for "
            f"{seconds:g} s, twice: alone, and with the churn beside them through the same data plane, "
            "one update at a time (the controller's own updates wait behind the churn's).  The paper "
            "counts entries (a TP of 6 joints is 12 in two tables); ours is one row a TP.",
            {
                "robots": n,
                "churn_update_ms_mean": float(np.mean(ms)),
                "latency_us_mean_quiet": lat["quiet"],
                "latency_us_mean_churn": lat["churn"],
                "latency_us_p99_quiet": quiet.latency_us_p99,
                "latency_us_p99_churn": busy.latency_us_p99,
                "path_error_mm_median_quiet": quiet.path_error_mm_median,
                "path_error_mm_median_churn": busy.path_error_mm_median,
                "path_error_mm_p99_quiet": quiet.path_error_mm_p99,
                "path_error_mm_p99_churn": busy.path_error_mm_p99,
            },
            caption="Top: the TPs in the data plane's tables over the run (the arms' own and the "
            "churn's), insertion and removal phases shaded.  Bottom: the arms' status-to-command time "
            "(each dot the mean over one 4 ms interval's answers) and its 0.25 s moving average, with "
            "and without the churn.",
            headline=(
                "insertion does not affect latency",
                f"mean {lat['quiet']:.0f} / {lat['churn']:.0f} us, path error median "
                f"{quiet.path_error_mm_median:.3f} / {busy.path_error_mm_median:.3f} mm (without / with)",
            ),
            verdict="yes" if held else "no",
        )
    ]


def resources(quick: bool, out: Path, log: Log) -> list[Section]:
    """Fig. 13a-b for our two targets: what the tables take for 50/100/200 TPs an arm, measured on
    the loaded XDP object (map memory, instructions) and on the numpy Tables (allocated memory)."""
    import tracemalloc

    from cell.config import load_config
    from cell.dataplane.tables import Tables

    cfg = load_config(None).dataplane
    arms = (100, 500, 1000) if quick else (100, 250, 500, 750, 1000)
    per_arm = (50, 100, 200)
    numpy_mb: dict[tuple[int, int], float] = {}
    for a in arms:
        for k in per_arm:
            tracemalloc.start()
            tables = Tables(a * k, cfg.max_entities)
            numpy_mb[a, k] = tracemalloc.get_traced_memory()[0] / 1e6
            tracemalloc.stop()
            del tables
    xdp_mb: dict[tuple[int, int], float] = {}
    why, res = "", None
    try:
        from cell.dataplane.xdp.program import XdpProgram

        for a in arms:
            for k in per_arm:
                prog = XdpProgram(a * k, cfg.n_bits, 6)
                try:
                    res = prog.resources()
                finally:
                    prog.close()
                xdp_mb[a, k] = res.map_bytes / 1e6
        assert res is not None  # (arms and per_arm are not empty)
        log(f"  XDP program: {res.programs['velocity_control']} (instructions, verified, JIT bytes)")
    except Exception as exc:  # (no BPF here: root, libbpf, the object)
        why = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
        log(f"  resources: the XDP object not loaded ({why})")
    plt = plt_()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for k, colour in zip(per_arm, ("tab:blue", "tab:orange", "tab:green"), strict=True):
        ax.plot(arms, [numpy_mb[a, k] for a in arms], "--s", color=colour, ms=3, label=f"numpy, {k} TPs/arm")
        if xdp_mb:
            ax.plot(
                arms, [xdp_mb[a, k] for a in arms], "-o", color=colour, ms=3, label=f"XDP maps, {k} TPs/arm"
            )
    ax.axvline(50_000 / 100, color="tab:red", lw=0.8)
    ax.text(
        50_000 / 100,
        ax.get_ylim()[1] * 0.9,
        " Tofino: 50K TPs\n (500 arms x 100)",
        color="tab:red",
        fontsize=7,
    )
    ax.set_xlabel("arms")
    ax.set_ylabel("memory (MB)")
    ax.legend(fontsize=6)
    top = (arms[-1], per_arm[-1])
    slope_x = (
        (xdp_mb[top] - xdp_mb[arms[0], per_arm[0]]) * 1e6 / (top[0] * top[1] - arms[0] * per_arm[0])
        if xdp_mb
        else float("nan")
    )
    slope_n = (numpy_mb[top] - numpy_mb[arms[0], per_arm[0]]) * 1e6 / (top[0] * top[1] - arms[0] * per_arm[0])
    rows = [
        ("TPs held", "at most 50K (the switch's SRAM)",
         f"{top[0] * top[1]:,} loaded here ({top[0]:,} arms x {top[1]}); the map's size is set at load, "
         "memory-bound"),
        ("memory a TP", "6 entries in two exact-match tables",
         f"{slope_x:.0f} B (XDP rows map), {slope_n:.0f} B (numpy Tables)"),
        ("memory, numpy / XDP maps", "-",
         f"{numpy_mb[top]:.1f} / {xdp_mb.get(top, float('nan')):.1f} MB at {top[0]:,} arms x {top[1]} TPs"),
    ]  # fmt: skip
    figures: dict[str, Any] = {f"numpy_mb_{a}x{k}": v for (a, k), v in numpy_mb.items()}
    figures |= {f"xdp_map_mb_{a}x{k}": v for (a, k), v in xdp_mb.items()}
    figures |= {"bytes_per_tp_xdp": slope_x, "bytes_per_tp_numpy": slope_n}
    if res is not None:
        insns, verified, jited = res.programs["velocity_control"]
        fixed = sum(b for name, (_, b) in res.maps.items() if name != "rows")
        rows += [
            ("stages / instructions", "stages grow with the arms (big tables span stages)",
             f"{insns:,} instructions ({verified:,} verified, {jited:,} B JIT-compiled): the same for any "
             "number of arms"),
            ("per-robot and per-entity state (registers)", "-",
             f"{fixed / 1e6:.1f} MB fixed: {res.maps['robots'][0]:,} robot ids, "
             f"{res.maps['entities'][0]:,} entities"),
            ("TCAM (the approximation tables)", "limited; set by the precision alone",
             f"transform map {res.maps['transform'][1] / 1e3:.0f} KB at n_bits = {cfg.n_bits}, for any arms"),
        ]  # fmt: skip
        figures |= {"instructions": insns, "verified_instructions": verified, "jit_bytes": jited}
    return [
        Section(
            "resources",
            "Resources against arms",
            "Appendix A, Fig. 13a-b",
            rows,
            save(fig, out, "resources.png"),
            "Each XDP point is the program loaded with its rows map sized for arms x TPs an arm, the map "
            "memory read from the kernel (fdinfo memlock) and the instructions from bpf_prog_info; each "
            "numpy point the memory a Tables of that capacity allocates (tracemalloc)."
            + (f"  The XDP object was not loaded here: {why}." if why else ""),
            figures,
            caption="Memory the tables take against the number of arms, for 50, 100 and 200 TPs an arm, "
            "on both targets, with the paper's switch limit.",
            headline=(
                "linear in arms; 50K TPs at most",
                f"linear, {slope_x:.0f} B a TP (XDP); {top[0] * top[1]:,} TPs loaded",
            ),
            verdict="yes" if xdp_mb else "scaled",
        )
    ]


ID0 = 1_000_000  # the parked TPs' first id


def _t_upd_fit(t: dict[int, float]) -> tuple[float, float]:
    """t_upd(n) = fixed + per_tp n, fitted (ms, ms a TP); the fixed part no less than the least seen."""
    per_tp, fixed = np.polyfit(np.array(list(t), float), np.array(list(t.values())), 1)
    return max(fixed, min(t.values())), per_tp


async def _t_upd(
    sizes: tuple[int, ...], robots: int, reps: int, arms_to_check: Callable[[dict[int, float]], int]
) -> tuple[dict[int, float], tuple[float, int, float]]:
    """t_upd through a live data plane service, as a controller sees it (request to reply over the
    bus): for each size n, one update inserting n TPs and removing the n loaded before (ms, median
    of reps).  Then, on the same service, the check: arms_to_check(those t_upd) updates of one 1 s
    episode each (10 TPs) sent at once, and how long the data plane took to apply them all
    (episode s, arms, s)."""
    from cell.bench.fleet import dealt
    from cell.bus import Bus
    from cell.cellproc import running_cell
    from cell.dataplane.client import DataplaneClient

    ids = np.arange(1, robots + 1)
    rob = [{"id": int(r), "name": f"e{r}", "skill_port": 20000 + int(r), "socket": "shared"} for r in ids]
    overrides = {"robots": rob, "services": {"run": ["bus", "dataplane"]}}
    t_upd: dict[int, float] = {}
    async with running_cell(overrides, quiet=True) as config, Bus.connect(config.bus, "bench-tupd") as bus:
        dp = DataplaneClient(bus, timeout=30.0)
        first = 0
        for n in sizes:
            await dp.update(insert=dealt(ids, first, n, ID0))
            times = []
            for _ in range(reps):
                old = dealt(ids, first, n, ID0)
                t0 = time.perf_counter()
                await dp.update(insert=dealt(ids, first + n, n, ID0), remove=old.keys)
                times.append((time.perf_counter() - t0) * 1e3)
                first += n
            old = dealt(ids, first, n, ID0)
            await dp.update(remove=old.keys)
            first += n
            t_upd[n] = float(np.median(times))
        episode_s, arms = 1.0, min(arms_to_check(t_upd), robots)
        n = max(1, round(10 * episode_s))
        batches = [dealt(ids[r : r + 1], first + r * n, n, ID0) for r in range(arms)]
        t0 = time.perf_counter()
        await asyncio.gather(*(dp.update(insert=b) for b in batches))
        spent = time.perf_counter() - t0
        await asyncio.gather(*(dp.update(remove=b.keys) for b in batches))
    return t_upd, (episode_s, arms, spent)


def episodes(quick: bool, out: Path, log: Log) -> list[Section]:
    """Fig. 13c-d: how many arms the control plane can keep fed, against the episode length and the
    TP rate, from t_upd measured through the live data plane service."""
    from cell.config import load_config

    cap = load_config(None).dataplane.capacity
    sizes = (1, 10, 100, 400, 1600) if quick else (1, 10, 100, 400, 1600, 6400)

    def arms_fed(t: dict[int, float], ep: np.ndarray, rate: float) -> np.ndarray:
        """One update an episode for each arm, applied one after another: arms x t_upd(n) <= t_ep; and
        3 episodes of each arm in the tables."""
        fixed, per_tp = _t_upd_fit(t)
        n = rate * ep
        return np.minimum(ep * 1e3 / (fixed + per_tp * n), cap / (3 * n))

    # the curve checked on the same service: the derived number of arms at 1 s episodes and 10 TPs/s,
    # their updates sent at once; the data plane must apply them all within the episode
    t, check = asyncio.run(
        _t_upd(sizes, 1000, 3 if quick else 7, lambda t: int(arms_fed(t, np.array([1.0]), 10)[0]))
    )
    for n, ms in t.items():
        log(f"  t_upd, {n:,} TPs in and {n:,} out: {ms:.2f} ms")
    log(f"  check: {check[1]} arms' 1 s episodes (10 TPs each) applied in {check[2]:.2f} s")
    n_arr = np.array(list(t), float)
    t0, c = _t_upd_fit(t)  # ms an update, ms a TP

    ep = np.logspace(-1, 1, 40)
    plt = plt_()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.2))
    a1.loglog(n_arr, list(t.values()), "o", label="measured")
    grid = np.logspace(0, np.log10(n_arr.max()), 30)
    a1.loglog(grid, t0 + c * grid, "-", lw=0.8, label=f"{t0:.2f} ms + {1e3 * c:.1f} us a TP")
    a1.axhline(300, color="tab:red", lw=0.8)
    a1.text(1, 180, "paper: ~300 ms for 1.6K TPs", color="tab:red", fontsize=7)
    a1.set_xlabel("TPs in and out in one update")
    a1.set_ylabel("t_upd (ms)")
    a1.legend(fontsize=7)
    for rate, style in ((10, "-"), (43, "--")):
        a2.loglog(ep, arms_fed(t, ep, rate), style, label=f"{rate} TPs/s")
    a2.plot([check[0]], [check[1]], "k*", ms=8, label=f"checked: {check[1]} arms in {check[2]:.2f} s")
    a2.plot([1.0], [500], "rX", label="paper: 500 arms, 1 s, 10 TPs/s")
    a2.set_xlabel("episode length t_ep (s)")
    a2.set_ylabel("arms kept fed")
    a2.legend(fontsize=7)
    at = {(e, r): float(arms_fed(t, np.array([e]), r)[0]) for e in (1.0, 10.0) for r in (10, 43)}
    t16 = t.get(1600, t0 + c * 1600)
    return [
        Section(
            "episodes",
            "Arms against episode length and TP rate",
            "Appendix A, Fig. 13c-d",
            [
                ("t_upd: 1.6K TPs in and 1.6K out", "~300 ms (linear, >= 1 ms)", f"{t16:.1f} ms"),
                ("t_upd: fixed part; a TP", "1 ms floor", f"{t0:.2f} ms; {1e3 * c:.2f} us"),
                (
                    "arms at 1 s episodes, 10 / 43 TPs/s",
                    "500 / -",
                    f"{at[1.0, 10]:,.0f} / {at[1.0, 43]:,.0f}",
                ),
                ("arms at 10 s episodes, 10 / 43 TPs/s", "-", f"{at[10.0, 10]:,.0f} / {at[10.0, 43]:,.0f}"),
                (
                    "checked: the derived arms' updates of one 1 s episode, sent at once",
                    "-",
                    f"{check[1]:,} updates applied in {check[2]:.2f} s",
                ),
            ],
            save(fig, out, "episodes.png"),
            "t_upd is measured as the controller sees it: one update request over the bus to the data "
            "plane service (numpy), n TPs inserted and the n loaded before removed, the median of "
            "several.  The arms it keeps fed: each arm needs one update an episode (its next episode "
            f"in, its last out), applied one at a time, and 3 episodes of it in the {cap:,} TPs.  The "
            "check sends that many updates at once and times them.",
            {
                "t_upd_ms_1600": t16,
                "t_upd_ms_fixed": t0,
                "t_upd_us_per_tp": 1e3 * c,
                "arms_1s_10tps": at[1.0, 10],
                "arms_1s_43tps": at[1.0, 43],
                "checked_arms": check[1],
                "checked_s": check[2],
            }
            | {f"t_upd_ms_{n}": v for n, v in t.items()},
            caption="Left: t_upd against the TPs one update adds and removes, measured, with its linear "
            "fit.  Right: the arms whose episodes the control plane keeps loading, against the episode "
            "length, at 10 and 43 TPs/s.",
            headline=("500 arms at 1 s episodes, 10 TPs/s", f"{at[1.0, 10]:,.0f} arms"),
            verdict="yes" if at[1.0, 10] >= 500 and check[2] <= check[0] else "no",
        )
    ]


def x86(quick: bool, out: Path, log: Log) -> list[Section]:
    """App. B: the host-side driver, one process per arm as the paper's ROS driver node, against
    the data plane, on one core each, at 500 Hz x 6 joints."""
    from cell.bench import dataplane

    seconds = 2.0 if quick else 4.0
    one = dataplane.trial("drivers", 1, seconds)
    log(dataplane.format_trial(one) + f", {one.cpu_cores:.3f} cores")
    found = dataplane.sustained("drivers", 2, seconds, log=lambda t: log(dataplane.format_trial(t)))
    drivers = found.best.robots if found.best is not None else 0
    sizes = (100,) if quick else (100, 300)
    planes = [dataplane.trial("dataplane", n, seconds) for n in sizes]
    for t in planes:
        log(dataplane.format_trial(t) + f", {t.cpu_cores:.3f} cores")
    big = planes[-1]
    per_core_dp = big.robots / big.cpu_cores if big.cpu_cores > 0 else float("nan")
    plt = plt_()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    # each fleet size once: its best trial (the search counts a size when one of its two trials passes)
    best: dict[int, float] = {}
    for t in found.trials:
        if not t.limit:
            best[t.robots] = max(best.get(t.robots, 0.0), 100 * t.on_time_fraction)
    fleets = sorted(best)
    ax.plot(fleets, [best[n] for n in fleets], "o-", label="a driver per arm")
    ax.plot(
        [t.robots for t in planes], [100 * t.on_time_fraction for t in planes], "s-", label="the data plane"
    )
    ax.axhline(99, color="k", lw=0.8)
    ax.axvline(45 / 12, color="tab:red", lw=0.8)
    ax.set_ylim(0, 105)
    ax.text(45 / 12, 50, " paper: 45 arms\n on 12 cores", color="tab:red", fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("arms at 500 Hz, on one core")
    ax.set_ylabel("statuses answered in the window (%)")
    ax.legend(fontsize=7)
    return [
        Section(
            "x86",
            "Host-side drivers against the data plane",
            "Appendix B",
            [
                (
                    "CPU of one arm's driver",
                    "0.42 of a core connected (0.19 idle)",
                    f"{one.cpu_cores:.3f} of a core",
                ),
                (
                    "arms on one core, a driver process each",
                    "45 on 12 cores (3.75 a core)",
                    f"{drivers} (>= 99 % of statuses answered within 8 ms)",
                ),
                (
                    "arms on one core, the data plane",
                    "500-1000 on one switch",
                    f"{big.robots} on {big.cpu_cores:.2f} of a core ({per_core_dp:,.0f} a core)",
                ),
                (
                    "status to command p50 / p99: drivers / data plane",
                    "-",
                    f"{one.p50_us:.0f} / {one.p99_us:.0f} us (1 arm); {big.p50_us:.0f} / {big.p99_us:.0f} us "
                    f"({big.robots} arms)",
                ),
            ],
            save(fig, out, "x86.png"),
            "The driver (cell.bench.driver) takes each status datagram as it comes, computes the "
            "command in floating point and answers: the shape of the paper's ROS driver node, without "
            "ROS.  Both run pinned to the second core, the load generator to the first.",
            {
                "driver_cpu_cores": one.cpu_cores,
                "driver_arms_per_core": drivers,
                "dataplane_arms": big.robots,
                "dataplane_cpu_cores": big.cpu_cores,
                "dataplane_arms_per_core": per_core_dp,
            },
            caption="Statuses answered within the command window against the arms on one core: one "
            "driver process per arm, and the data plane serving them all.",
            headline=(
                "45 arms on 12 cores (x86 drivers)",
                f"{drivers} a core (drivers), {per_core_dp:,.0f} (data plane)",
            ),
            verdict="yes" if per_core_dp > 10 * max(drivers, 1) else "no",
        )
    ]
