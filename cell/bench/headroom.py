"""`cell bench headroom`: how much of its core the cell's real-time packet path leaves free.

Two measurements, each next to its baseline in the same run:

- the tick: one MuJoCo arm's tick (send, take, step, pack) timed call by call, in C
  (cell/robot/tick.c) and in Python (the reference model, `tick = "python"`);
- the cell: the default cell (two MuJoCo arms) idle, then moving (both arms back and forth through
  the controller), with the CPU its packet path's processes use (robots, which runs the Responsive
  Link's hub too, and the data plane), the holds of their real-time threads (runnable, not run:
  cell/sched.Held), and each command's time from its status leaving the robot to its arrival back
  (kernel stamps, measured at the robot); then the same for the cell as it ran before the native
  loops (`tick = "python"`, `backend = "numpy"`), unless --no-baseline.

The default cell's data plane is the XDP program where it can run (as root: status -> command aim
50 us), else the native one (200 us).  --config FILE measures a cell with FILE's settings over the
default (e.g. `[dataplane] backend = "native"`); the baseline stays the default cell as it ran
before the native loops.

The JSON line (last) has packet_path_cpu_pct_idle, packet_path_cpu_pct_moving, tick_us_p99,
rt_holds and status_to_command_us_p99 (issue 53), and the baseline's figures beside them.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import time
import tomllib
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell import aio, sched
from cell.bench.registry import Bench, Figures, log, register
from cell.bus import Bus, FaultCode, RemoteError
from cell.cellproc import default_robots, robots_heard, running_cell
from cell.config import CellConfig, load_config
from cell.jsonfields import OMIT_IF_NONE, JsonFields
from cell.launcher import fetch_status
from cell.ports import free_port
from cell.sched import process_cpu_seconds
from cell.v1 import controller_pb2

PACKET_PATH = ("robots", "dataplane")  # the processes of the packet path (rlink's hub runs in robots')
AIMS = {"packet_path_cpu_pct_idle": 5.0, "packet_path_cpu_pct_moving": 10.0, "tick_us_p99": 30.0}
S2C_AIM_US = {"xdp": 50.0, "native": 200.0}  # status -> command p99: in the kernel, in user space


def tick_times(tick: str, n: int) -> np.ndarray:
    """n ticks of one MuJoCo arm (`tick`: "native" or "python"), each timed (us; C's in C), a UDP sink
    for its status and nothing commanding it."""
    from cell.robot import udp
    from cell.robot.emulator import RobotGroup

    robots = [{"id": 1, "name": "h1", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 0}]
    cfg = load_config(overrides={"robots": robots})
    sink = udp.open_socket("127.0.0.1")
    host, port = sink.getsockname()
    group = RobotGroup(cfg.robots, f"{host}:{port}", tick=tick)
    if group.tick_impl != tick:
        raise RuntimeError(f"the {tick} tick cannot run here: {group.tick_why}")
    out = np.empty(n)
    native = group.native
    try:
        for i in range(n + 100):  # (the first 100: warm-up)
            if native is not None:  # (timed in C: the tick's work, not the ctypes call's)
                took = native.lib.rg_tick_timed(native._ref, float("inf"), 1) / 1e3
            else:
                t0 = time.perf_counter_ns()
                group.tick(float("inf"))
                took = (time.perf_counter_ns() - t0) / 1e3
            if i >= 100:
                out[i - 100] = took
            if i % 64 == 0:
                while udp.recv_batch(sink) is not None:  # (the sink's buffer never fills)
                    pass
    finally:
        group.close()
        sink.close()
    return out


async def _pids(config: Any) -> dict[str, int]:
    status = await fetch_status(config)
    return {s.name: s.last.pid for s in status.services if s.name in PACKET_PATH}


async def _counters(config: Any) -> dict[str, dict[str, float]]:
    status = await fetch_status(config)
    return {s.name: dict(s.last.counters) for s in status.services if s.name in PACKET_PATH}


def _cpu(pids: dict[str, int]) -> float:
    return sum(process_cpu_seconds(p) for p in set(pids.values()))


def _holds(c: dict[str, dict[str, float]]) -> float:
    return sum(s.get("process.rt.held", 0.0) for s in c.values())


@contextlib.asynccontextmanager
async def _mover(bus: Bus, config: CellConfig) -> AsyncIterator[Callable[[str, np.ndarray], Awaitable]]:
    """move(robot, goal): a joint move at 80 % on the cell's own controller service when it runs one
    (a second controller would take its robots over: docs/controller.md), else on one of ours."""
    from cell.controller.controller import Controller

    if config.runs("controller"):

        async def over_the_bus(robot: str, goal: np.ndarray) -> None:
            req = controller_pb2.MoveRequest(robot=robot, values=goal.tolist(), speed=80.0)
            await bus.request("controller", "move", req, controller_pb2.MoveReply, 60.0)

        async with asyncio.timeout(20):  # (until the service has the robots: their pose answered)
            for name in ("r1", "r2"):
                while True:
                    try:
                        pose = controller_pb2.RobotRequest(robot=name)
                        await bus.request("controller", "pose", pose, controller_pb2.PoseReply, 5.0)
                        break
                    except RemoteError:
                        await asyncio.sleep(0.1)
        yield over_the_bus
        return
    async with Controller(bus, config) as ctl:
        await robots_heard(ctl, {1, 2})
        yield lambda robot, goal: ctl.move_joints(robot, goal, speed=0.8)


async def cell_figures(overrides: dict[str, Any], idle_s: float, moving_s: float) -> dict[str, float]:
    """One cell's figures: its packet path's CPU idle and moving, RT holds, status -> command p99."""
    from cell.controller.motion import MotionStopped, NotAtGoal

    q0 = np.array(load_config(None).robots[0].q0)
    async with (
        running_cell({"robots": default_robots(), **overrides}, quiet=True) as config,
        Bus.connect(config.bus, "bench-headroom") as bus,
        _mover(bus, config) as move,
    ):
        pids = await _pids(config)
        await asyncio.sleep(1.0)  # (start-up's work done)
        held0 = _holds(await _counters(config))
        cpu0, t0 = _cpu(pids), time.monotonic()
        await asyncio.sleep(idle_s)
        idle = (_cpu(pids) - cpu0) / (time.monotonic() - t0) * 100
        cpu0, t0 = _cpu(pids), time.monotonic()
        rng, k, failed = np.random.default_rng(53), 0, 0
        while time.monotonic() - t0 < moving_s:  # both arms back and forth, as the demo's moves
            goal = q0 + rng.uniform(-0.4, 0.4, 6) if k % 2 == 0 else q0
            ends = await asyncio.gather(*(move(r, goal) for r in ("r1", "r2")), return_exceptions=True)
            # (a motion the packet path could not carry, e.g. the baseline's on a slow day: its robot
            # protective-stopped, is a figure of the cell measured, not the bench's end)
            for end in ends:
                if isinstance(end, MotionStopped | NotAtGoal) or (
                    isinstance(end, RemoteError) and end.code in (FaultCode.STOPPED, FaultCode.FAILED)
                ):
                    failed += 1
                    log(f"a motion failed: {end}")
                elif isinstance(end, BaseException):
                    raise end
            k += 1
        moving = (_cpu(pids) - cpu0) / (time.monotonic() - t0) * 100
        c = await _counters(config)
    rb = c.get("robots", {})
    return {
        "cpu_pct_idle": idle,
        "cpu_pct_moving": moving,
        "rt_holds": _holds(c) - held0,
        "status_to_command_us_p99": rb.get("answer_p99_us", float("nan")),
        "missed_ticks": rb.get("missed_ticks", 0.0),
        "protective_stops": rb.get("protective_stops", 0.0),
        "moves": float(k),
        "moves_failed": float(failed),
    }


@dataclass
class HeadroomResult(JsonFields):
    """The tick in C and in Python, the default cell's packet path idle and moving (issue 53's keys),
    and the baseline cell's figures (cell_figures' keys, each as baseline_<key>) if it ran."""

    tick_us_p50: float
    tick_us_p99: float
    python_tick_us_p99: float
    tick_speedup_p99: float
    tick_placed: str
    backend: str  # the measured cell's data plane (the baseline's is numpy)
    packet_path_cpu_pct_idle: float
    packet_path_cpu_pct_moving: float
    rt_holds: float
    status_to_command_us_p99: float
    missed_ticks: float
    protective_stops: float
    moves_failed: float  # the arms' motions (two a move) the cell did not carry to their goals
    baseline_cpu_pct_idle: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_cpu_pct_moving: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_rt_holds: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_status_to_command_us_p99: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_missed_ticks: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_protective_stops: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_moves: float | None = field(default=None, metadata=OMIT_IF_NONE)
    baseline_moves_failed: float | None = field(default=None, metadata=OMIT_IF_NONE)


def run(
    quick: bool, baseline: bool, idle_s: float, moving_s: float, config_path: str | None = None
) -> HeadroomResult:
    """config_path: a cell config whose settings go over the default's for the measured cell (a bad
    file is said in one line, exit 2, before anything starts: load_config raises ConfigError)."""
    backend = load_config(config_path).dataplane.chosen()[0]
    user = tomllib.loads(Path(config_path).read_text()) if config_path else {}
    n = 2000 if quick else 20000
    log(f"one MuJoCo arm's tick, {n} times, in C and in Python (CPU 1, SCHED_FIFO 70: as the robots run)")
    affinity, policy = os.sched_getaffinity(0), os.sched_getscheduler(0)
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    placed = sched.place([1], 70, -10)  # (the robots' process's place: the tick timed, not the VM's noise)
    try:
        native, python = tick_times("native", n), tick_times("python", n)
    finally:
        os.sched_setscheduler(0, policy, os.sched_param(0))
        os.sched_setaffinity(0, affinity)
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    tick_p99, python_p99 = float(np.percentile(native, 99)), float(np.percentile(python, 99))
    which = f"{config_path} over the default" if config_path else "the default cell"
    log(f"{which} (native tick, {backend} data plane): {idle_s:g} s idle, {moving_s:g} s moving")
    now = aio.run(cell_figures(user, idle_s, moving_s))
    result = HeadroomResult(
        tick_us_p50=float(np.percentile(native, 50)),
        tick_us_p99=tick_p99,
        python_tick_us_p99=python_p99,
        tick_speedup_p99=python_p99 / tick_p99,
        tick_placed="; ".join(placed) or "cpu 1, fifo 70",
        backend=backend,
        packet_path_cpu_pct_idle=now["cpu_pct_idle"],
        packet_path_cpu_pct_moving=now["cpu_pct_moving"],
        rt_holds=now["rt_holds"],
        status_to_command_us_p99=now["status_to_command_us_p99"],
        missed_ticks=now["missed_ticks"],
        protective_stops=now["protective_stops"],
        moves_failed=now["moves_failed"],
    )
    if baseline:
        log("the baseline: the same cell with the Python tick and the numpy data plane")
        was = {"robot_defaults": {"tick": "python"}, "dataplane": {"backend": "numpy"}}
        old = aio.run(cell_figures(was, idle_s, moving_s))
        result.baseline_cpu_pct_idle = old["cpu_pct_idle"]
        result.baseline_cpu_pct_moving = old["cpu_pct_moving"]
        result.baseline_rt_holds = old["rt_holds"]
        result.baseline_status_to_command_us_p99 = old["status_to_command_us_p99"]
        result.baseline_missed_ticks = old["missed_ticks"]
        result.baseline_protective_stops = old["protective_stops"]
        result.baseline_moves = old["moves"]
        result.baseline_moves_failed = old["moves_failed"]
    return result


def format_result(r: HeadroomResult) -> str:
    lines = [
        f"one MuJoCo arm's tick: p50 {r.tick_us_p50:.1f} us, p99 {r.tick_us_p99:.1f} us in C "
        f"(aim <= {AIMS['tick_us_p99']:g}); p99 {r.python_tick_us_p99:.1f} us in Python "
        f"({r.tick_speedup_p99:.1f}x)",
        "packet path CPU (robots + data plane + rlink), % of a core: "
        f"idle {r.packet_path_cpu_pct_idle:.1f} "
        f"(aim <= {AIMS['packet_path_cpu_pct_idle']:g}), moving {r.packet_path_cpu_pct_moving:.1f} "
        f"(aim <= {AIMS['packet_path_cpu_pct_moving']:g})",
        f"RT holds {r.rt_holds:.0f} (aim 0), status -> command p99 {r.status_to_command_us_p99:.0f} us "
        f"at the robot (aim <= {S2C_AIM_US.get(r.backend, S2C_AIM_US['native']):g} on the {r.backend} "
        f"data plane), missed ticks {r.missed_ticks:.0f}, protective stops {r.protective_stops:.0f}, "
        f"motions failed {r.moves_failed:.0f}",
    ]
    if r.baseline_cpu_pct_idle is not None:
        lines.append(
            f"baseline (Python tick, numpy data plane): idle {r.baseline_cpu_pct_idle:.1f} %, moving "
            f"{r.baseline_cpu_pct_moving:.1f} %, RT holds {r.baseline_rt_holds:.0f}, status -> "
            f"command p99 {r.baseline_status_to_command_us_p99:.0f} us, missed ticks "
            f"{r.baseline_missed_ticks:.0f}, protective stops {r.baseline_protective_stops:.0f}, motions "
            f"failed {r.baseline_moves_failed:.0f} of {2 * (r.baseline_moves or 0):.0f}"
        )
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="short phases, no baseline (make test's check)")
    p.add_argument("--idle-s", type=float, default=None, help="seconds idle (default 10; quick 2)")
    p.add_argument("--moving-s", type=float, default=None, help="seconds moving (default 10; quick 2)")
    p.add_argument("--no-baseline", action="store_true", help="skip the cell as before (Python, numpy)")
    p.add_argument(
        "--config",
        "-c",
        metavar="FILE",
        help="a cell config merged over the default for the measured cell (e.g. examples/xdp.toml)",
    )


def _main(args: argparse.Namespace) -> Figures:
    idle = args.idle_s if args.idle_s is not None else (2.0 if args.quick else 10.0)
    moving = args.moving_s if args.moving_s is not None else (2.0 if args.quick else 10.0)
    result = run(args.quick, not (args.quick or args.no_baseline), idle, moving, args.config)
    return Figures(result, format_result(result))


register(
    Bench(
        "headroom",
        "the packet path's CPU, RT holds and tick time: native loops next to the Python ones",
        _arguments,
        _main,
    )
)
