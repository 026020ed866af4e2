"""`cell bench ur`: the emulated arms' UR interfaces as UR's clients see them.

- RTDE output at 500 Hz, read by a separate client process (a plain RTDE client on raw sockets, so
  the arrival times are its own): the period between packages' arrivals, p50/p99, and packages
  missed (gaps in their `timestamp`) per 10,000, for 1 arm and for 20 arms of one cell.  Beside
  it, the baseline: how late the arms' own ticks started (the robots' lateness p99), the machine's
  share of the jitter.
- servoJ: ur_rtde's RTDEControlInterface in its own process streams a 1 Hz sine at 500 Hz through
  servoJ (lookahead 0.1 s) while it reads actual_q; the lag that best aligns the arm with the
  commands, and the largest error at that lag.  Then the same through UR's own client library's
  path: the external_control program and a servoj target every 2 ms on its reverse interface.
- The secondary interface (30002): how many robot state packages a client gets a second (a UR
  sends 10); beside it, the real-time interface (30003): its state messages a second (a UR: 500).

- The daemon (`backend = "ur"`): one cell, two MuJoCo arms driven side by side through the same data
  plane by the same controller with the same motions (the accuracy bench's joint moves and straight
  lines), one directly over datagrams, one reached only over its UR interfaces through the daemon.
  The tool path error at every TP against the plan (ground truth for the direct arm, the truth the
  daemon reads over RTDE for the other), and the daemon's own added latency: an RTDE package in ->
  its status datagrams out, and the package that ends a command window -> that window's register
  write out (the window's wait itself is the arm's, on both paths).
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import queue
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cell.bench.accuracy import Q0, tool_errors_mm
from cell.bench.registry import Bench, Figures, log, register
from cell.bus import Bus
from cell.cellproc import robots_heard, running_cell
from cell.controller.controller import Controller
from cell.jsonfields import JsonFields
from cell.launcher import fetch_status
from cell.ports import free_port
from cell.robot.kinematics import Kinematics
from cell.robot.truth import Truth
from cell.ur import primary, realtime, robotstate, rtde
from cell.ur.external import MULT, REVERSE, Mode, client_program
from cell.ur.rtde import Package
from cell.ur.urscript import EXTERNAL_SOCKETS

PERIOD_S = 0.002


def _robots(n: int, backend: str) -> list[dict[str, Any]]:
    return [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": backend, "truth_hz": 0}
        for i in range(1, n + 1)
    ]


async def _read_rtde(host: str, port: int, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(arrival ns, timestamp s) of each `timestamp` package at 500 Hz for `seconds`."""
    reader, writer = await asyncio.open_connection(host, port)
    writer.write(rtde.encode(Package.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)))
    writer.write(rtde.encode(Package.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 500.0) + b"timestamp"))
    writer.write(rtde.encode(Package.CONTROL_PACKAGE_START))
    buf = bytearray()
    arrivals: list[int] = []
    stamps: list[float] = []
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while loop.time() < end:
        try:
            async with asyncio.timeout(1.0):
                data = await reader.read(65536)
        except TimeoutError:
            continue
        if not data:
            break
        now = time.monotonic_ns()
        buf += data
        for kind, body in rtde.split(buf):
            if kind == Package.DATA_PACKAGE and len(body) == 9:
                arrivals.append(now)
                stamps.append(struct.unpack_from(">d", body, 1)[0])
    writer.close()
    return np.array(arrivals, np.int64), np.array(stamps)


def _client(hosts: list[str], port: int, seconds: float, out: Any) -> None:
    """The separate client process: every arm's stream at once."""

    async def main() -> list[tuple[np.ndarray, np.ndarray]]:
        return await asyncio.gather(*(_read_rtde(h, port, seconds) for h in hosts))

    out.put(asyncio.run(main()))


def _servo_client(host: str, seconds: float, out: Any) -> None:
    """ur_rtde's own servoJ loop in its own process (its calls hold the GIL)."""
    import rtde_control
    import rtde_receive

    ctl = rtde_control.RTDEControlInterface(host)
    recv = rtde_receive.RTDEReceiveInterface(host)
    q0 = np.array(recv.getActualQ())
    cmd, got = [], []
    for k in range(int(seconds / PERIOD_S)):
        t0 = ctl.initPeriod()
        q = q0.copy()
        q[0] += 0.1 * np.sin(2 * np.pi * k * PERIOD_S)
        ctl.servoJ(q.tolist(), 0.0, 0.0, PERIOD_S, 0.1, 300)
        cmd.append(q[0])
        got.append(recv.getActualQ()[0])
        ctl.waitPeriod(t0)
    ctl.servoStop(4.0)
    ctl.stopScript()
    ctl.disconnect()
    recv.disconnect()
    out.put((np.array(cmd), np.array(got)))


def _external_servo_client(host: str, primary_port: int, seconds: float, out: Any) -> None:
    """UR's client library's servoj loop, as its ROS 2 driver runs it, in its own process: the
    external_control program sent headless to the primary interface, the arm connecting back to
    this process's three servers, a target every 2 ms on the reverse interface (read timeout 20 ms,
    servoj lookahead 0.03 s and gain 2000: the library's defaults), actual_q read over RTDE."""
    import socket

    import rtde_receive

    servers = {name: socket.create_server(("127.0.0.1", 0)) for name in EXTERNAL_SOCKETS}
    ports = {name: s.getsockname()[1] for name, s in servers.items()}
    with socket.create_connection((host, primary_port)) as primary_interface:
        primary_interface.sendall(client_program("127.0.0.1", ports).encode())
        conns = {}
        for name, server in servers.items():
            server.settimeout(10)
            conns[name] = server.accept()[0]
            conns[name].setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # (as URCL's servers)
        recv = rtde_receive.RTDEReceiveInterface(host)
        q0 = np.array(recv.getActualQ())
        reverse = conns["reverse_socket"]
        cmd, got = [], []
        t_next = time.perf_counter()
        for k in range(int(seconds / PERIOD_S)):
            q = q0.copy()
            q[0] += 0.1 * np.sin(2 * np.pi * k * PERIOD_S)
            reverse.sendall(REVERSE.pack(20, *(round(v * MULT) for v in q), Mode.SERVOJ))
            cmd.append(q[0])
            got.append(recv.getActualQ()[0])
            t_next += PERIOD_S
            time.sleep(max(0.0, t_next - time.perf_counter()))
        reverse.sendall(REVERSE.pack(0, 0, 0, 0, 0, 0, 0, Mode.STOPPED))
        recv.disconnect()
        for c in conns.values():
            c.close()
    out.put((np.array(cmd), np.array(got)))


def _in_process(target: Any, *args: Any, timeout: float) -> Any:
    """target(*args, queue) in a process of its own (a client as users run it, its own GIL); what it
    put on the queue.  A child that dies first says so at once, not at the timeout."""
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, out), daemon=True)
    proc.start()
    deadline = time.monotonic() + timeout
    try:
        while True:
            try:
                return out.get(timeout=0.5)
            except queue.Empty:
                if not proc.is_alive() and out.empty():
                    why = f"{target.__name__} ended (exit code {proc.exitcode}) with no result"
                    raise RuntimeError(why) from None
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{target.__name__} gave no result in {timeout:.0f} s") from None
    finally:
        proc.join(5)
        if proc.is_alive():
            proc.kill()


def _periods(streams: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    periods = np.concatenate([np.diff(a) / 1e6 for a, _ in streams if a.size > 1])
    missed = expected = 0
    for _, ts in streams:
        if ts.size > 1:
            steps = np.rint(np.diff(ts) / PERIOD_S).astype(np.int64)
            missed += int((steps - 1).clip(min=0).sum())
            expected += int(steps.sum())
    return {
        "period_ms_p50": float(np.percentile(periods, 50)),
        "period_ms_p99": float(np.percentile(periods, 99)),
        "missed_per_10k": 1e4 * missed / max(expected, 1),
        "packages": int(sum(a.size for a, _ in streams)),
    }


async def _rtde_run(n: int, seconds: float, backend: str) -> tuple[dict[str, float], float]:
    robots = _robots(n, backend)
    overrides = {"services": {"run": ["bus", "dataplane", "robots"]}, "robots": robots}
    async with running_cell(overrides) as config:
        hosts = [r.ur_host for r in config.robots]
        streams = await asyncio.to_thread(
            _in_process, _client, hosts, config.ur.rtde_port, seconds, timeout=seconds + 30
        )
        status = await fetch_status(config)
        robots_status = next(s for s in status.services if s.name == "robots").last.counters
    return _periods(streams), float(robots_status.get("lateness_p99_us", float("nan")))


async def _state_run(seconds: float, backend: str) -> tuple[float, float]:
    """The robot state packages a client of the secondary interface (30002) gets a second, and the
    state messages one of the real-time interface (30003) gets, side by side (wall clock)."""
    overrides = {"services": {"run": ["bus", "dataplane", "robots"]}, "robots": _robots(1, backend)}
    async with running_cell(overrides) as config:
        host = config.robots[0].ur_host

        async def rate(port: int, count: Callable[[bytearray], int]) -> float:
            reader, writer = await asyncio.open_connection(host, port)
            try:
                buf, seen = bytearray(), list[float]()
                async with asyncio.timeout(seconds + 10):
                    while not seen or seen[-1] - seen[0] < seconds:
                        buf += await reader.read(65536)
                        seen += [time.monotonic()] * count(buf)
            finally:
                writer.close()
            return (len(seen) - 1) / (seen[-1] - seen[0])

        def states(buf: bytearray) -> int:
            return sum(kind == robotstate.ROBOT_STATE for kind, _ in primary.split(buf))

        state_hz, realtime_hz = await asyncio.gather(
            rate(config.ur.secondary_port, states),
            rate(config.ur.realtime_port, lambda buf: len(realtime.split(buf))),
        )
        return state_hz, realtime_hz


async def _servo_run(seconds: float, backend: str, external: bool = False) -> tuple[float, float]:
    """servoJ's lag and error: ur_rtde's servoJ, or (external) UR's client library's servoj over
    the external_control program's reverse interface."""
    overrides = {"services": {"run": ["bus", "dataplane", "robots"]}, "robots": _robots(1, backend)}
    async with running_cell(overrides) as config:
        host = config.robots[0].ur_host
        how: tuple[Any, ...] = (
            (_external_servo_client, host, config.ur.primary_port, seconds)
            if external
            else (_servo_client, host, seconds)
        )
        cmd, got = await asyncio.to_thread(_in_process, *how, timeout=seconds + 30)
    tail = slice(len(cmd) // 4, len(cmd))
    lags = range(0, min(100, tail.start))
    err = [float(np.abs(cmd[tail.start - k : tail.stop - k] - got[tail]).max()) for k in lags]
    lag = int(np.argmin(err))
    return lag * PERIOD_S * 1000, err[lag] * 1000


async def _demo(ctl: Controller, kin: Kinematics, truth: Truth, name: str, moves: int) -> np.ndarray:
    """The accuracy bench's motions on one robot: path errors at every TP (mm)."""
    errors = []

    async def measured() -> None:
        seg = ctl.track(name).segment
        assert seg is not None
        await truth.until(name, seg.end_ns + 10_000_000)  # (every TP's truth in before it is read)
        errors.append(tool_errors_mm(kin, truth, name, seg, slice(0, 6)))

    rng = np.random.default_rng(7)
    for _ in range(moves):
        await ctl.move_joints(name, Q0 + rng.uniform(-0.6, 0.6, 6), speed=0.6)
        await measured()
    await ctl.move_joints(name, Q0, speed=0.6)
    pos, rot = kin.fk(Q0)
    for leg in [(0.2, 0, 0), (0, 0.2, 0), (-0.2, 0, 0), (0, -0.2, 0)]:
        pos = pos + np.array(leg)
        await ctl.move_linear(name, pos, rot, speed=1.0)
        await measured()
    log(f"{name}: path error max per motion (mm) " + ", ".join(f"{e.max():.2f}" for e in errors))
    return np.concatenate(errors)


async def _bridge_run(moves: int) -> dict[str, float]:
    robots = [
        {"id": 1, "name": "r1", "skill_port": free_port(), "backend": "mujoco", "truth_hz": 500},
        {"id": 2, "name": "r2", "skill_port": free_port(), "backend": "ur", "ur_emulate": "mujoco",
         "truth_hz": 500},
    ]  # fmt: skip
    overrides = {"services": {"run": ["bus", "dataplane", "robots"]}, "robots": robots}
    kin = Kinematics()
    async with running_cell(overrides) as config, Bus.connect(config.bus, "bench-ur") as bus:
        async with Truth.watching(bus) as truth, Controller(bus, config) as ctl:
            await robots_heard(ctl, {1, 2})
            # one after the other, so that neither path pays for the other's load
            direct = await _demo(ctl, kin, truth, "r1", moves)
            daemon = await _demo(ctl, kin, truth, "r2", moves)
        status = await fetch_status(config)
        c = next(s for s in status.services if s.name == "robots").last.counters
    return {
        "direct_path_error_mm_max": float(direct.max()),
        "direct_path_error_mm_median": float(np.median(direct)),
        "bridge_path_error_mm_max": float(daemon.max()),
        "bridge_path_error_mm_median": float(np.median(daemon)),
        "bridge_status_us_p50": c["daemon.status_us_p50"],
        "bridge_status_us_p99": c["daemon.status_us_p99"],
        "bridge_write_us_p50": c["daemon.write_us_p50"],
        "bridge_write_us_p99": c["daemon.write_us_p99"],
        "bridge_latency_us_p99": max(c["daemon.status_us_p99"], c["daemon.write_us_p99"]),
        "bridge_echo_ms_p50": c.get("daemon.echo_ms_p50", float("nan")),
        "bridge_cycles_missed": c["daemon.cycles_missed"],
    }


@dataclass
class UrResult(JsonFields):
    """RTDE's period and misses (1 arm, then `arms`), the ticks' lateness, servoJ's lag and error,
    and the daemon bridge's latency and path error next to the direct path's (_bridge_run's keys)."""

    arms: int
    backend: str
    rtde_period_ms_p50: float
    rtde_period_ms_p99: float
    rtde_missed_per_10k: float
    rtde_period_ms_p99_20_arms: float
    rtde_missed_per_10k_20_arms: float
    tick_lateness_p99_us: float
    tick_lateness_p99_us_20_arms: float
    servoj_lag_ms: float
    servoj_error_mrad: float
    external_control_servoj_lag_ms: float
    external_control_servoj_error_mrad: float
    primary_state_hz: float
    realtime_state_hz: float
    direct_path_error_mm_max: float
    direct_path_error_mm_median: float
    bridge_path_error_mm_max: float
    bridge_path_error_mm_median: float
    bridge_status_us_p50: float
    bridge_status_us_p99: float
    bridge_write_us_p50: float
    bridge_write_us_p99: float
    bridge_latency_us_p99: float
    bridge_echo_ms_p50: float
    bridge_cycles_missed: float


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="each RTDE stream's length (default 10)")
    p.add_argument("--arms", type=int, default=20, help="arms of the many-arm run (default 20)")
    p.add_argument("--servo-seconds", type=float, default=5.0, help="the servoJ run (default 5)")
    p.add_argument("--backend", default="kinematic", choices=["kinematic", "mujoco"])
    p.add_argument("--moves", type=int, default=5, help="random joint moves of the daemon run (default 5)")


def _main(args: argparse.Namespace) -> Figures:
    async def run() -> UrResult:
        one, late1 = await _rtde_run(1, args.seconds, args.backend)
        log(
            f"RTDE, 1 arm: period p50 {one['period_ms_p50']:.3f} ms, p99 {one['period_ms_p99']:.3f} ms, "
            f"{one['missed_per_10k']:.2f} missed per 10k ({one['packages']} packages; ticks' lateness "
            f"p99 {late1:.0f} us)"
        )
        many, late_n = await _rtde_run(args.arms, args.seconds, args.backend)
        log(
            f"RTDE, {args.arms} arms: period p50 {many['period_ms_p50']:.3f} ms, p99 "
            f"{many['period_ms_p99']:.3f} ms, {many['missed_per_10k']:.2f} missed per 10k "
            f"({many['packages']} packages; ticks' lateness p99 {late_n:.0f} us)"
        )
        state_hz, realtime_hz = await _state_run(args.seconds, args.backend)
        log(
            f"secondary interface (30002): the robot state at {state_hz:.2f} Hz (a UR: 10); real-time "
            f"interface (30003): its state at {realtime_hz:.1f} Hz (a UR: 500)"
        )
        lag, err = await _servo_run(args.servo_seconds, args.backend)
        log(f"servoJ, 500 Hz, 1 Hz sine, lookahead 0.1 s: lag {lag:.0f} ms, then off by {err:.2f} mrad")
        ext_lag, ext_err = await _servo_run(args.servo_seconds, args.backend, external=True)
        log(
            f"external_control servoj (UR's client library's loop), 500 Hz, lookahead 0.03 s: lag "
            f"{ext_lag:.0f} ms, then off by {ext_err:.2f} mrad"
        )
        b = await _bridge_run(args.moves)
        log(
            f"daemon: RTDE package -> status datagrams p50 {b['bridge_status_us_p50']:.0f} us, p99 "
            f"{b['bridge_status_us_p99']:.0f} us; window end -> register write p50 "
            f"{b['bridge_write_us_p50']:.0f} us, p99 {b['bridge_write_us_p99']:.0f} us; the program took "
            f"each window {b['bridge_echo_ms_p50']:.1f} ms after (p50)"
        )
        log(
            f"tool path error at TPs, the same motions side by side: direct max "
            f"{b['direct_path_error_mm_max']:.2f} mm (median {b['direct_path_error_mm_median']:.3f}), "
            f"through the daemon max {b['bridge_path_error_mm_max']:.2f} mm "
            f"(median {b['bridge_path_error_mm_median']:.3f})"
        )
        return UrResult(
            arms=args.arms,
            backend=args.backend,
            rtde_period_ms_p50=one["period_ms_p50"],
            rtde_period_ms_p99=one["period_ms_p99"],
            rtde_missed_per_10k=one["missed_per_10k"],
            rtde_period_ms_p99_20_arms=many["period_ms_p99"],
            rtde_missed_per_10k_20_arms=many["missed_per_10k"],
            tick_lateness_p99_us=late1,
            tick_lateness_p99_us_20_arms=late_n,
            servoj_lag_ms=lag,
            servoj_error_mrad=err,
            external_control_servoj_lag_ms=ext_lag,
            external_control_servoj_error_mrad=ext_err,
            primary_state_hz=state_hz,
            realtime_state_hz=realtime_hz,
            direct_path_error_mm_max=b["direct_path_error_mm_max"],
            direct_path_error_mm_median=b["direct_path_error_mm_median"],
            bridge_path_error_mm_max=b["bridge_path_error_mm_max"],
            bridge_path_error_mm_median=b["bridge_path_error_mm_median"],
            bridge_status_us_p50=b["bridge_status_us_p50"],
            bridge_status_us_p99=b["bridge_status_us_p99"],
            bridge_write_us_p50=b["bridge_write_us_p50"],
            bridge_write_us_p99=b["bridge_write_us_p99"],
            bridge_latency_us_p99=b["bridge_latency_us_p99"],
            bridge_echo_ms_p50=b["bridge_echo_ms_p50"],
            bridge_cycles_missed=b["bridge_cycles_missed"],
        )

    result = asyncio.run(run())
    return Figures(result)


register(
    Bench(
        "ur",
        "the UR interfaces: RTDE at 500 Hz (1, 20 arms), servoJ's lag, the daemon's latency and path error",
        _arguments,
        _main,
        description=__doc__,
    )
)
