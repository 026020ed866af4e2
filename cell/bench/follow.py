"""`cell bench follow`: trajectories planned elsewhere, run on MuJoCo arms of a real cell.

By default (issue 55) an out-and-back 1 - cos on all six joints, with positions and velocities, at 8,
40 and 250 points a second over 3.5 s each on r1, then two arms on one trajectory each at 20 points a
second started together: the tool path error at the points (from ground truth at 500 Hz,
interpolated), the TPs a second the fitting used (cell.controller.tps.fit_led) and the two arms'
start shift, each against its own plan.

`--long` (issue 35): a 10-minute, 30,000-point trajectory with the controller's memory sampled all
along.  The cell runs with one service a process (`--layout each`), so the controller's resident
memory is its own (/proc/<pid>/status VmRSS, the pid from `cell status`).  Figures: the
controller's RSS after loading, at the end, its largest and its slope over the run (MB/min: flat is
~0), and the path error.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cell.bench.registry import Bench, Figures, log, register
from cell.bus import Bus
from cell.cellproc import running_cell
from cell.jsonfields import JsonFields
from cell.launcher import fetch_status
from cell.ports import free_port
from cell.robot.arm import arm_model
from cell.robot.truth import Truth
from cell.trajectory.model import Trajectory
from cell.trajectory.wire import to_message
from cell.v1 import controller_pb2

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
AMPLITUDE = np.array([0.5, -0.3, 0.3, 0.4, 0.4, 0.6])  # rad, each joint's swing
CYCLES_PER_10_MIN = np.array([30, 42, 54, 66, 78, 90])  # whole periods: at rest where it began


def long_trajectory(points: int, seconds: float) -> Trajectory:
    t = np.linspace(0.0, seconds, points)
    f = np.maximum(1, np.round(CYCLES_PER_10_MIN * seconds / 600.0)) / seconds  # (as fast, however long)
    q = Q0 + AMPLITUDE * (1 - np.cos(2 * np.pi * np.outer(t, f))) / 2
    return Trajectory.build(t, q, name=f"long-{points}")


DENSITIES = (8, 40, 250)  # points a second of the plans the fitting is measured on
DENSE_S = 3.5
DUAL_PPS = 20
DUAL_AMPLITUDE = np.array([-0.5, 0.3, -0.2, 0.4, -0.3, 0.6])


def out_and_back(pps: float, seconds: float, amplitude: np.ndarray = AMPLITUDE) -> Trajectory:
    """Every joint out and back on 1 - cos, at rest at both ends: positions and velocities, as a
    planner writes them."""
    t = np.linspace(0.0, seconds, round(pps * seconds) + 1)
    w = 2 * np.pi / seconds
    q = Q0 + amplitude * (1 - np.cos(w * t))[:, None] / 2
    qd = amplitude * (w * np.sin(w * t))[:, None] / 2
    return Trajectory.build(t, q, qd, name=f"out-and-back-{pps:g}")


@dataclass
class AccuracyResult(JsonFields):
    """The tool path error at the points (mm) at each density, the fitting's TPs a second, and two
    arms started together (their worse error, and their start shift against their plans, ms)."""

    path_error_mm_max_8: float
    path_error_mm_median_8: float
    path_error_mm_max_40: float
    path_error_mm_median_40: float
    path_error_mm_max_250: float
    path_error_mm_median_250: float
    tps_per_s_8: float
    tps_per_s_40: float
    tps_per_s_250: float
    fitted_deviation_mm_max: float
    dual_path_error_mm_max: float
    dual_path_error_mm_median: float
    dual_start_shift_ms: float


async def _follow(
    bus: Bus, config, trajs: dict[str, Trajectory]
) -> tuple[dict[str, np.ndarray], float, float, float]:
    """The trajectories followed together: each robot's tool error at its points (mm), the start
    shift (ms), the fitting's TPs a second and its modelled deviation (mm)."""
    arm = arm_model("ur5e")
    req = controller_pb2.FollowRequest(
        speed=50.0,
        trajectories=[to_message(r, t.t, t.q, t.qd, name=t.name) for r, t in trajs.items()],
    )
    longest = max(t.duration for t in trajs.values())
    async with Truth.watching(bus) as truth:
        reply = await bus.request("controller", "follow", req, controller_pb2.MoveReply, timeout=longest + 60)
        for r in trajs:
            await truth.until(r, reply.t_end_ns + 20_000_000)
    errors, starts = {}, []
    for r, traj in trajs.items():
        q_real = truth.at(r, reply.t0_ns + traj.t * 1e9)
        errors[r] = (
            np.array(
                [np.linalg.norm(arm.fk(a)[0] - arm.fk(b)[0]) for a, b in zip(q_real, traj.q, strict=True)]
            )
            * 1e3
        )
        moved = truth.start_of_motion(r, reply.t0_ns - 20_000_000)
        starts.append(moved - reply.t0_ns - traj.starts_moving_s() * 1e9)
    return errors, (max(starts) - min(starts)) / 1e6, reply.tps_per_s, reply.fitted_deviation_mm


async def _accuracy() -> AccuracyResult:
    robots = [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 500}
        for i in (1, 2)
    ]
    overrides = {"services": {"run": ["bus", "dataplane", "robots", "controller"]}, "robots": robots}
    figures: dict[str, float] = {}
    deviation = 0.0
    async with running_cell(overrides) as config, Bus.connect(config.bus, "bench-follow") as bus:
        for pps in DENSITIES:
            errors, _, tps, dev = await _follow(bus, config, {"r1": out_and_back(pps, DENSE_S)})
            e = errors["r1"]
            log(
                f"{pps} points/s: error at the points max {e.max():.4f} mm, "
                f"median {np.median(e):.4f} mm; {tps:.1f} TP/s"
            )
            figures[f"path_error_mm_max_{pps}"] = round(float(e.max()), 4)
            figures[f"path_error_mm_median_{pps}"] = round(float(np.median(e)), 4)
            figures[f"tps_per_s_{pps}"] = round(tps, 1)
            deviation = max(deviation, dev)
        dual = {"r1": out_and_back(DUAL_PPS, DENSE_S), "r2": out_and_back(DUAL_PPS, DENSE_S, DUAL_AMPLITUDE)}
        errors, shift, _, dev = await _follow(bus, config, dual)
        both = np.concatenate(list(errors.values()))
        deviation = max(deviation, dev)
    return AccuracyResult(
        **figures,
        fitted_deviation_mm_max=round(deviation, 4),
        dual_path_error_mm_max=round(float(both.max()), 4),
        dual_path_error_mm_median=round(float(np.median(both)), 4),
        dual_start_shift_ms=round(shift, 3),
    )


@dataclass
class FollowResult(JsonFields):
    """The controller's memory (MB, to 0.1; its slope in MB/min) and the tool path error (mm)."""

    points: int
    duration_s: float
    controller_rss_mb_before: float
    controller_rss_mb_loaded: float
    controller_rss_mb_end: float
    controller_rss_mb_max: float
    controller_rss_mb_per_min: float
    path_error_mm_max: float
    path_error_mm_median: float


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


async def _run(points: int, seconds: float, sample_s: float) -> FollowResult:
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 250}]
    overrides = {
        "services": {"run": ["bus", "dataplane", "robots", "controller"], "layout": "each"},
        "robots": robots,
    }
    traj = long_trajectory(points, seconds)
    arm = arm_model("ur5e")
    async with running_cell(overrides) as config, Bus.connect(config.bus, "bench-follow") as bus:
        status = await fetch_status(config)
        pid = next(s.last.pid for s in status.services if s.name == "controller")
        samples: list[tuple[float, float]] = []
        req = controller_pb2.FollowRequest(
            speed=50.0, trajectories=[to_message("r1", traj.t, traj.q, name=traj.name)]
        )
        rss_before = rss_mb(pid)
        t0 = time.monotonic()
        async with Truth.watching(bus) as truth:
            follow = asyncio.ensure_future(
                bus.request("controller", "follow", req, controller_pb2.MoveReply, timeout=seconds + 120.0)
            )
            try:
                while not follow.done():
                    samples.append((time.monotonic() - t0, rss_mb(pid)))
                    await asyncio.wait([follow], timeout=sample_s)
                reply = follow.result()
            finally:
                follow.cancel()
            await truth.until("r1", reply.t_end_ns + 20_000_000)
        q_real = truth.at("r1", reply.t0_ns + traj.t * 1e9)
    err = (
        np.array([np.linalg.norm(arm.fk(a)[0] - arm.fk(b)[0]) for a, b in zip(q_real, traj.q, strict=True)])
        * 1e3
    )
    s = np.array(samples)
    steady = s[s[:, 0] >= min(30.0, seconds / 4)]  # after the load and the first episodes
    slope = float(np.polyfit(steady[:, 0] / 60.0, steady[:, 1], 1)[0]) if len(steady) >= 3 else float("nan")
    return FollowResult(
        points=points,
        duration_s=seconds,
        controller_rss_mb_before=round(rss_before, 1),
        controller_rss_mb_loaded=round(float(steady[0, 1]) if len(steady) else float(s[0, 1]), 1),
        controller_rss_mb_end=round(float(s[-1, 1]), 1),
        controller_rss_mb_max=round(float(s[:, 1].max()), 1),
        controller_rss_mb_per_min=round(slope, 3),
        path_error_mm_max=round(float(err.max()), 4),
        path_error_mm_median=round(float(np.median(err)), 4),
    )


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--long", action="store_true", help="the long trajectory and the controller's memory")
    p.add_argument("--minutes", type=float, default=10.0, help="--long: its length (default 10)")
    p.add_argument("--points", type=int, default=30_000, help="--long: its points (default 30,000)")
    p.add_argument("--quick", action="store_true", help="--long: 1 minute, 3,000 points")
    p.add_argument("--sample-s", type=float, default=5.0, help="--long: the memory sampled this often")


def _main(args: argparse.Namespace) -> Figures:
    if not args.long:
        log(f"out and back at {', '.join(map(str, DENSITIES))} points/s, then two arms at {DUAL_PPS}")
        a = asyncio.run(_accuracy())
        text = (
            "tool path error at the points, max / median mm: "
            + ", ".join(
                f"{pps}/s {getattr(a, f'path_error_mm_max_{pps}'):.3f} / "
                f"{getattr(a, f'path_error_mm_median_{pps}'):.4f} ({getattr(a, f'tps_per_s_{pps}'):.0f} TP/s)"
                for pps in DENSITIES
            )
            + f"; two arms {a.dual_path_error_mm_max:.3f} / {a.dual_path_error_mm_median:.4f}, start shift "
            f"{a.dual_start_shift_ms:.2f} ms"
        )
        return Figures(a, text)
    minutes, points = (1.0, 3_000) if args.quick else (args.minutes, args.points)
    every = args.sample_s
    log(f"following {points:,} points over {minutes:g} min on a MuJoCo arm (its memory every {every:g} s)")
    r = asyncio.run(_run(points, minutes * 60.0, args.sample_s))
    text = (
        f"controller RSS {r.controller_rss_mb_before} MB before, {r.controller_rss_mb_loaded} MB "
        f"loaded, {r.controller_rss_mb_end} MB at the end (max {r.controller_rss_mb_max}), slope "
        f"{r.controller_rss_mb_per_min:+.3f} MB/min; tool path error at the points max "
        f"{r.path_error_mm_max:.3f} mm, median {r.path_error_mm_median:.4f} mm"
    )
    return Figures(r, text, section="follow --long")


register(
    Bench(
        "follow",
        "trajectories at 8, 40, 250 points/s and two arms on MuJoCo arms: the path error (--long: memory)",
        _arguments,
        _main,
        description=__doc__,
    )
)
