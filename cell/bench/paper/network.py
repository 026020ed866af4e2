"""`cell bench paper`'s experiments on the packet path: response time (Sec. 7.1), resubmission
(Algorithm 1) and background traffic (App. C)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cell.bench.paper.page import Log, Section, paper_line, plt_, save

if TYPE_CHECKING:
    from cell.bench.dataplane import Trial


def latency(quick: bool, out: Path, log: Log) -> list[Section]:
    from cell.bench import dataplane

    seconds = 2.0 if quick else 3.0
    trials = [dataplane.trial("dataplane", n, seconds) for n in ((10, 100) if quick else (10, 100, 300))]
    for t in trials:
        log(dataplane.format_trial(t))
    plt = plt_()
    fig, ax = plt.subplots(figsize=(6, 3))
    x = np.arange(len(trials))
    ax.bar(x - 0.2, [t.p50_us for t in trials], 0.4, label="p50")
    ax.bar(x + 0.2, [t.p99_us for t in trials], 0.4, label="p99")
    ax.set_xticks(x, [f"{t.robots} robots" for t in trials])
    ax.set_yscale("log")
    paper_line(ax, 1.3, "Tofino 0.6-1.3 us")
    ax.set_ylabel("status to command (us)")
    ax.legend(fontsize=7)
    lat = Section(
        "latency",
        "Response time",
        "Sec. 7.1, Fig. 14",
        [
            (f"status to command, {t.robots} robots, p50 / p99", "0.6-1.3 us (Tofino, 64 B)", _us(t))
            for t in trials
        ]
        + [
            (
                "answered within the 8 ms command window",
                ">= 99 %",
                f"{100 * trials[-1].on_time_fraction:.2f} %",
            )
        ],
        save(fig, out, "latency.png"),
        "A load generator on one core plays the robots (real UDP on loopback); the data plane runs on "
        "the other.  With background traffic at a congested port: see Appendix C below.",
        {f"p99_us_{t.robots}": t.p99_us for t in trials} | {f"p50_us_{t.robots}": t.p50_us for t in trials},
        caption="Status-to-command time through the data plane (log scale), median and p99, per fleet "
        "size, with the paper's Tofino figure.",
        headline=("0.6-1.3 us (Tofino)", f"{_us(trials[-1])} ({trials[-1].robots} robots)"),
        verdict="scaled" if trials[-1].on_time_fraction >= 0.99 else "no",
    )
    return [lat]


def _us(t: Trial) -> str:
    return f"{t.p50_us:.0f} / {t.p99_us:.0f} us"


def resubmission(quick: bool, out: Path, log: Log) -> list[Section]:
    """Algorithm 1 steps a trajectory once per pass: a status that finds k TPs due takes k passes (k-1
    resubmissions).  Measured on the real pipeline with 100 robots at 500 Hz."""
    from cell.dataplane.pipeline import ControlConstants, Pipeline
    from cell.dataplane.tables import Tables, TPBatch
    from cell.robot import datagram
    from cell.robot.datagram import Kind

    robots, period = 100, 2_000_000
    rows = []
    figures: dict[str, Any] = {}
    rates = (10, 500, 1000, 2000)
    ticks = 200 if quick else 1000
    cost = {}
    for rate in rates:
        t = Tables(capacity=robots * 4100)
        pipe = Pipeline(t, ControlConstants((1.0,) * 6, (2.0,) * 6, 8, (np.pi,) * 6))
        n_tp = 4000
        for r in range(1, robots + 1):
            t.add_robot(r)
            ids = np.arange(n_tp)
            nxt = np.append(ids[1:], 0)  # a loop: the trajectory never runs out
            zeros = np.zeros((n_tp, 6))
            t.insert(
                TPBatch(np.full(n_tp, r), ids, nxt, np.full(n_tp, 1 / rate), np.full(n_tp, 6), zeros, zeros)
            )
            t.set_registers(r, 0, 0)
        recs0 = datagram.empty(robots * 6)
        datagram.pack(
            recs0,
            np.repeat(np.arange(1, robots + 1), 6),
            np.tile(np.arange(6), robots),
            Kind.STATUS,
            1,
            0.0,
            0.0,
        )
        spent = 0
        for k in range(ticks):
            recs = recs0.copy()
            recs["seq"] = k + 1
            t0 = time.perf_counter_ns()
            pipe.process(recs, k * period)
            spent += time.perf_counter_ns() - t0
        c = pipe.counters
        per_step = c.resubmits / max(c.steps, 1)
        cost[rate] = spent / (ticks * robots * 6)
        figures[f"resubmits_per_step_{rate}hz"] = per_step
        figures[f"ns_per_packet_{rate}hz"] = cost[rate]
        rows.append(
            (f"TP rate {rate} Hz: resubmissions per TP step; time per status", "1 per extra step",
             f"{per_step:.2f}; {cost[rate]:.0f} ns")
        )  # fmt: skip
        log(f"TP rate {rate} Hz: {c.steps} steps, {c.resubmits} resubmissions, {cost[rate]:.0f} ns a status")
    plt = plt_()
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.plot(rates, [cost[r] for r in rates], "o-")
    ax.set_xscale("log")
    ax.set_xlabel("TP rate (Hz), status 500 Hz x 6 joints")
    ax.set_ylabel("pipeline time per status (ns)")
    lo, hi = cost[rates[0]], cost[rates[-1]]
    busiest = figures[f"resubmits_per_step_{rates[-1]}hz"]
    return [
        Section(
            "resubmission",
            "Resubmission",
            "Sec. 5, Algorithm 1",
            rows,
            save(fig, out, "resubmission.png"),
            "A status packet steps its trajectory at most once per pass through the pipeline, as a "
            "switch reads a register once per pass: with TPs due faster than statuses come, each "
            "further step is a resubmission (counted as the paper counts them: every step of an "
            "entity after its first in a batch of packets).  Each further step is one more "
            "vectorised pass over the entities that have one due, not one more pass per packet: the "
            f"time per status grows from {lo:.0f} to {hi:.0f} ns ({hi / lo:.1f}x) from {rates[0]} to "
            f"{rates[-1]} TP/s, where {busiest:.2f} of the steps are resubmissions.",
            figures,
            caption="The pipeline's time per status packet (100 robots) against the TP rate: above the "
            "status rate, TPs come due faster than packets and steps are resubmitted.",
            headline=(
                "1 resubmission per extra step",
                f"{busiest:.2f} of the steps at {rates[-1]} TP/s, none at {rates[0]} TP/s",
            ),
            verdict="yes" if figures[f"resubmits_per_step_{rates[0]}hz"] == 0 and busiest > 0 else "no",
        )
    ]


def background(quick: bool, out: Path, log: Log) -> list[Section]:
    from cell.bench import background as bg

    why = bg.available()
    if why:
        log(f"  background: skipped, {why}")
        return [
            Section(
                "background",
                "Background traffic and priority queueing",
                "Appendix C, Fig. 14",
                notes=f"Not run: this experiment {why}.",
                headline=("FIFO ~3 ms and losses at 9 Gbps; priority sub-ms", "-"),
            )
        ]
    r = bg.run(quick, log=log)
    top, low = max(bg.QUICK_LOADS), min(bg.QUICK_LOADS)
    plt = plt_()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    for sched, color in (("fifo", "tab:red"), ("priority", "tab:green")):
        for frame, style in ((64, "-o"), (1280, "--s")):
            pts = [x for x in r.rows if x.scheduling == sched and x.frame == frame]
            loads = [x.load for x in pts]
            label = f"{sched}, {frame} B"
            axes[0].plot(loads, [x.p50_us / 1e3 for x in pts], style, color=color, label=label)
            axes[0].fill_between(
                loads,
                [x.p50_us / 1e3 for x in pts],
                [x.p99_us / 1e3 for x in pts],
                color=color,
                alpha=0.12,
            )
            axes[1].plot(loads, [100 * x.lost_fraction for x in pts], style, color=color, label=label)
    axes[0].set_xlabel(f"load offered to the port (x its {r.rate_mbps:g} Mbit/s)")
    axes[0].set_ylabel("robot response time (ms), p50-p99")
    axes[1].set_xlabel(axes[0].get_xlabel())
    axes[1].set_ylabel("robot packets lost (%)")
    axes[0].legend(fontsize=7)

    def at(sched: str, load: float, key: str, agg: Callable[..., float] = max) -> float:
        return agg(getattr(x, key) for x in r.at(sched, load))

    return [
        Section(
            "background",
            "Background traffic and priority queueing",
            "Sec. 7.1, Appendix C, Fig. 14",
            [
                (
                    "port rate; buffer",
                    "5 Gbit/s; (3 ms seen)",
                    f"{r.rate_mbps:g} Mbit/s; {r.buffer_ms:g} ms",
                ),
                (
                    "response time at 0.2x load (1 Gbps of 5), p50",
                    "~1 us",
                    f"{at('fifo', low, 'p50_us', min) / 1e3:.2f}-{at('fifo', low, 'p50_us') / 1e3:.2f} ms",
                ),
                (
                    f"one FIFO, {top:g}x load (9 Gbps of 5): p50 / lost",
                    "~3 ms; some (5 Gbps) to almost all (9) lost",
                    f"{at('fifo', top, 'p50_us') / 1e3:.2f} ms / "
                    f"{100 * at('fifo', top, 'lost_fraction', min):.0f}-"
                    f"{100 * at('fifo', top, 'lost_fraction'):.0f} % (over the two frame sizes)",
                ),
                (
                    f"strict priority, {top:g}x load: p99 / lost",
                    "sub-millisecond; 0",
                    f"{at('priority', top, 'p99_us') / 1e3:.2f} ms / "
                    f"{100 * at('priority', top, 'lost_fraction'):.2f} %",
                ),
            ],
            save(fig, out, "background.png"),
            "Robots, a traffic generator and the data plane in three network namespaces made for the run; "
            "the data plane answers the robots and port-forwards the ordinary traffic through one egress "
            "port (cell.dataplane.egress), 10% of the load robot commands, frames of 64 or 1,280 bytes "
            "(cell.bench.background).  The port is scaled to what a software switch forwards on one core "
            "here; the floor of our response time is this machine's (veth, Python, wake-ups), not a "
            "Tofino's.",
            bg.summary(r),
            caption="Robot response time (median, shaded to p99) and robot packets lost against the "
            "load offered to the egress port, one FIFO against strict priority for robot traffic.",
            headline=(
                "FIFO ~3 ms and losses at 9 Gbps; priority sub-ms, none lost",
                f"FIFO {at('fifo', top, 'p50_us') / 1e3:.1f} ms, priority p99 "
                f"{at('priority', top, 'p99_us') / 1e3:.2f} ms, "
                f"{100 * at('priority', top, 'lost_fraction'):.1f} % lost",
            ),
            verdict="scaled"
            if at("priority", top, "p99_us") < at("fifo", top, "p50_us")
            and at("priority", top, "lost_fraction") == 0
            else "no",
        )
    ]


# how long each experiment takes on this machine kind (2 cores), --quick and full: for the progress lines


def xdp_background(quick: bool, out: Path, log: Log) -> list[Section]:
    """Sec. 7.1's response time beside background traffic, on the XDP backend, against plain
    forwarding in the same run (cell.bench.background_xdp)."""
    from cell.bench import background_xdp as bx
    from cell.config import xdp_missing

    title, ref = "Response time with background traffic (XDP)", "Sec. 7.1"
    if why := xdp_missing():
        log(f"  xdp-background: skipped, {why}")
        return [
            Section(
                "xdp-background",
                title,
                ref,
                notes=f"Not run: the XDP backend {why}.",
                headline=("0.6-1.3 us, < 0.2 us from plain forwarding", "-"),
            )
        ]
    s = bx.sweep(quick, log=log)
    plt = plt_()
    fig, ax = plt.subplots(figsize=(6.5, 3.2))
    for frame, style in ((64, "-o"), (1280, "--s")):
        pts = [p for p in s.points if p.frame == frame]
        x = [p.offered_kpps for p in pts]
        for name, colour, med in (
            ("velocity control", "tab:green", "control_p50_us"),
            ("plain forwarding", "tab:gray", "forward_p50_us"),
        ):
            ax.plot(x, [getattr(p, med) for p in pts], style, color=colour, label=f"{name}, {frame} B")
    ax.set_ylim(bottom=0)
    ax.set_xlabel("ordinary frames through the program (thousands a second)")
    ax.set_ylabel("status to command, p50 (us)")
    ax.legend(fontsize=7)
    f = s.figures()
    worst = max((p.apart_us for p in s.points), default=float("nan"))
    rows = [
        (
            f"p50 at {f[f'offered_kpps_{fr}']:.0f} kpps of {fr} B: velocity control / plain forwarding",
            bx.PAPER[f"p50_{fr}"],
            f"{f[f'control_p50_us_{fr}']:.0f} / {f[f'forward_p50_us_{fr}']:.0f} us",
        )
        for fr in bx.FRAMES
    ]
    rows += [
        (
            f"p99 at {f[f'offered_kpps_{fr}']:.0f} kpps of {fr} B: velocity control / plain forwarding",
            "-",
            f"{f[f'control_p99_us_{fr}']:.0f} / {f[f'forward_p99_us_{fr}']:.0f} us",
        )
        for fr in bx.FRAMES
    ]
    rows.append(("the pipeline's own share (p50 apart), worst point", bx.PAPER["apart"], f"{worst:+.1f} us"))
    return [
        Section(
            "xdp-background",
            title,
            ref,
            rows,
            save(fig, out, "xdp-background.png"),
            "Ten robots' probes (6 joints at 500 Hz) through the XDP velocity-control program, every "
            "robot following a TP, then through the object's plain forwarding program, while ordinary "
            "frames pass through the same program at each rate (XDP_PASS to the switch's stack).  One "
            "switch namespace, its packets on core 1; the generator and the prober on core 0.  Our "
            "floor is veth, generic XDP and a user-space prober, not a Tofino's pipeline: the gap "
            "between the two programs is what compares.",
            f | {"apart_us_worst": worst},
            caption="Probe response time (median; p99 in the table) against the ordinary traffic through "
            "the program, for the velocity-control pipeline and plain forwarding, 64- and 1,280-byte "
            "frames.",
            headline=(
                "0.6-1.3 us; < 0.2 us from plain forwarding",
                f"{f['control_p50_us_64']:.0f} us; {worst:+.1f} us from plain forwarding",
            ),
            verdict="scaled" if worst < 0.5 * min(p.forward_p50_us for p in s.points) else "no",
        )
    ]
