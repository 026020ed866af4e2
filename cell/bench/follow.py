"""`cell bench follow`: a long trajectory planned elsewhere (issue 35: 10 minutes, 30,000 points) run
on a MuJoCo arm of a real cell, the controller service's memory sampled all along.

The cell runs with one service a process (`--layout each`), so the controller's resident memory is
its own (/proc/<pid>/status VmRSS, the pid from `cell status`).  The trajectory is every joint on
1 - cos waves of its own frequency, a whole number of periods long (at rest at both ends), as
time-stamped positions only; the controller fits their velocities, checks them, cuts TPs on them and
streams them in episodes.  Figures: the controller's RSS after loading, at the end, its largest and
its slope over the run (MB/min: flat is ~0), and the tool path error at the points (from ground
truth at 250 Hz, interpolated).
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
    p.add_argument("--minutes", type=float, default=10.0, help="the trajectory's length (default 10)")
    p.add_argument("--points", type=int, default=30_000, help="its points (default 30,000)")
    p.add_argument("--quick", action="store_true", help="1 minute, 3,000 points")
    p.add_argument("--sample-s", type=float, default=5.0, help="the controller's memory sampled this often")


def _main(args: argparse.Namespace) -> Figures:
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
    return Figures(r, text)


register(
    Bench(
        "follow",
        "a 10-minute, 30,000-point trajectory on a MuJoCo arm: the controller's memory, the path error",
        _arguments,
        _main,
        description=__doc__,
    )
)
