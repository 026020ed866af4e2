"""`cell bench snp`: the modular-robot control cycle over SnP-MrT (cell.snp.cycle).

A master process and N slave processes (one per joint) run the A/B/C/D
exchange at 1 kHz for a few seconds; printed: the cycle time (both queries
of a slave, from T1 to the second answer) p50/p99, the deadline-miss rate,
the clock offset each slave reached with SnP-TSP, next to the proposal's
budget of 0.3 ms per cycle for a six-joint robot.  Baseline in the same run:
one slave alone.
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
from typing import Any

import numpy as np

from cell import aio


def _master(joints: int, port_out: Any, stop: Any, out: Any) -> None:
    from cell.bench import pin
    from cell.snp.cycle import run_master

    pin(0)
    out.put(aio.run(run_master(joints, port_out, stop)))


def _slave(joint: int, port: int, seconds: float, budget_ns: int, out: Any) -> None:
    from cell.snp.cycle import run_slave

    out.put((joint, aio.run(run_slave(joint, port, seconds, budget_ns))))


def trial(slaves: int, seconds: float, budget_ns: int) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    port_q, out, stop = ctx.Queue(), ctx.Queue(), ctx.Event()
    master = ctx.Process(target=_master, args=(slaves, port_q, stop, out), daemon=True)
    master.start()
    port = port_q.get(timeout=30)
    procs = [
        ctx.Process(target=_slave, args=(j, port, seconds, budget_ns, out), daemon=True)
        for j in range(slaves)
    ]
    for p in procs:
        p.start()
    results = [out.get(timeout=seconds + 60) for _ in procs]
    stop.set()
    counters = out.get(timeout=30)
    for p in [*procs, master]:
        p.join(10)
    cycles = np.concatenate([np.array(r["cycles"]) for _, r in results]) / 1e3  # us
    n = sum(len(r["cycles"]) for _, r in results)
    missed = sum(r["misses"]["ab"] + r["misses"]["cd"] for _, r in results)
    return {
        "slaves": slaves,
        "cycles": n,
        "cycle_p50_us": float(np.median(cycles)),
        "cycle_p99_us": float(np.percentile(cycles, 99)),
        "miss_rate": missed / max(1, 2 * n),
        "sync_offset_us_max": max(abs(r["offset_ns"]) for _, r in results) / 1e3,
        "sync_delay_us_max": max(r["delay_ns"] for _, r in results) / 1e3,
        "budget_us": budget_ns / 1e3,
        "master": {k: float(v) for k, v in counters.items()},
    }


def run(slaves: int = 6, seconds: float = 3.0, budget_ns: int = 1_000_000) -> dict[str, Any]:
    return {"baseline": trial(1, seconds, budget_ns), "robot": trial(slaves, seconds, budget_ns)}


def format_result(r: dict[str, Any]) -> str:
    def line(t: dict[str, Any]) -> str:
        return (
            f"  {t['slaves']} slave(s), {t['cycles']} cycles at 1 kHz: cycle p50 {t['cycle_p50_us']:.0f} us, "
            f"p99 {t['cycle_p99_us']:.0f} us; {100 * t['miss_rate']:.2f}% of queries missed their "
            f"{t['budget_us']:.0f} us deadline (a guess was used); SnP-TSP offset error <= "
            f"{t['sync_offset_us_max']:.1f} us (round trip {t['sync_delay_us_max']:.0f} us)"
        )

    return "\n".join(
        [
            "modular-robot cycle over SnP-MrT (two time-bounded queries per joint per cycle); "
            "the proposal's budget: 300 us per cycle for six joints",
            line(r["baseline"]),
            line(r["robot"]),
        ]
    )


if __name__ == "__main__":  # pragma: no cover
    print(format_result(asyncio.run(asyncio.to_thread(run))))
