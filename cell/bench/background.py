"""`cell bench background`: robot traffic beside ordinary traffic at a congested egress port
(NSDI'22 Sec. 7.1 and Appendix C, Fig. 14).

Three network namespaces made for the run and removed after it, joined by two
veth pairs, with the data plane between them as the paper's switch:

    robots ns (10.77.1.2)  ==veth==  switch ns: the data plane  ==veth==  generator ns (10.77.2.2)
    R robots x 6 joints at 500 Hz     10.77.1.1: statuses -> commands        ordinary UDP traffic of
    + the sink of ordinary traffic    10.77.2.1:7000 -> 10.77.1.2:7001         64- or 1,280-byte frames

The data plane (the real service's packet path, cell.dataplane.plane) answers
every status through the full pipeline (each robot follows a TP) and
port-forwards the ordinary traffic to the robots' host, so commands and
forwarded frames leave by one egress port: `rate_mbps` with a buffer of
`buffer_ms` of it per queue, either one shared FIFO or strict priority with
robot commands first ([dataplane.egress]).  As in the paper, 10% of the load
offered to that port is robot traffic and the rest ordinary traffic, from 0.2
to 1.8 times the port's rate (the paper: 1-9 Gbps on a 5 Gbps bottleneck).
Robots' response time (status sent to command received, kernel timestamps
aside: the robots' own clock) and loss, per frame size, load and scheduling.

Scaled to this machine: a software switch on one core forwards far less than
a Tofino, so the port is 100 Mbit/s, not 5 Gbit/s (the whole figure scales
with it: a 3 ms buffer is 3 ms at either rate).  The generator sends with UDP
GSO and the switch takes bursts with GRO; the offered and forwarded rates are
reported, so a point the machine could not offer shows as such.  Needs root
(namespaces); traffic stays inside the namespaces it made.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

from cell.bench.frames import FRAMES, HEADERS
from cell.bench.registry import Bench, Failed, Figures, log, register

ROBOT_ADDR, SWITCH_R, SWITCH_G, GEN_ADDR = "10.77.1.2", "10.77.1.1", "10.77.2.1", "10.77.2.2"
STATUS_PORT, FORWARD_PORT, SINK_PORT = 50000, 7000, 7001
ROBOT_SHARE = 0.10  # of the load offered to the egress port (the paper's mix)
LOADS = (0.2, 0.6, 1.0, 1.4, 1.8)  # x the port's rate
QUICK_LOADS = (0.2, 1.0, 1.8)
BURST_BYTES = 2560  # the generator's smallest send: two 1,280-byte frames, forty 64-byte ones
COMMAND_BPS_PER_ROBOT = 6 * 500 * (24 + HEADERS) * 8  # six 24-byte commands at 500 Hz: 1.68 Mbit/s

Log = Callable[[str], None]


@dataclasses.dataclass
class Point:
    """One scheduling, frame size and load: what was offered and forwarded, and the robots' times."""

    scheduling: str  # "fifo" or "priority"
    frame: int  # bytes
    load: float  # x the port's rate
    offered_mbps: float
    forwarded_mbps: float
    p50_us: float
    p99_us: float
    max_us: float
    lost_fraction: float
    on_time_fraction: float


@dataclasses.dataclass
class Result:
    rate_mbps: float
    buffer_ms: float
    robots: int
    seconds: float
    rows: list[Point]
    took_s: float

    def at(self, scheduling: str, load: float) -> list[Point]:
        return [r for r in self.rows if r.scheduling == scheduling and r.load == load]

    def to_json(self) -> dict[str, Any]:
        """The JSON line: the paper's figures (keys named by the loads run, so not fields), then every
        point."""
        return summary(self) | {"rows": [dataclasses.asdict(r) for r in self.rows]}


# --- the namespaces ------------------------------------------------------------------------------


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


@contextlib.contextmanager
def namespaces() -> Iterator[dict[str, str]]:
    """The three namespaces and two veth pairs, removed (with the pairs) however the block ends."""
    tag = f"cbg{os.getpid() % 100000}"
    ns = {"switch": f"{tag}s", "robots": f"{tag}r", "gen": f"{tag}g"}
    try:
        for name in ns.values():
            _ip("netns", "add", name)
        for side, (here, there) in {"robots": (SWITCH_R, ROBOT_ADDR), "gen": (SWITCH_G, GEN_ADDR)}.items():
            a, b = f"{tag}{side[0]}a", f"{tag}{side[0]}b"
            _ip("link", "add", a, "netns", ns["switch"], "type", "veth", "peer", "name", b, "netns", ns[side])
            for n, dev, addr in ((ns["switch"], a, here), (ns[side], b, there)):
                _ip("-n", n, "addr", "add", f"{addr}/24", "dev", dev)
                _ip("-n", n, "link", "set", dev, "up")
        for name in ns.values():
            _ip("-n", name, "link", "set", "lo", "up")
        yield ns
    finally:
        for name in ns.values():
            subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=10)  # (its veths too)


def available() -> str | None:
    """Why this bench cannot run here, or None."""
    if os.geteuid() != 0:
        return "needs root (network namespaces)"
    try:
        subprocess.run(["ip", "-V"], check=True, capture_output=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "needs `ip` (iproute2)"
    return None


def _role(ns: str, role: str, *args: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, "-m", "cell.bench.background", role, *args]


# --- the three roles (each a process in its namespace) ---------------------------------------------


def switch_main(robots: int, rate_mbps: float, buffer_kb: float, scheduling: str) -> None:
    """The data plane as the switch: answers statuses, forwards ordinary traffic, until SIGTERM;
    prints its counters as one JSON line."""
    from cell.bench import pin
    from cell.config import load_config
    from cell.dataplane.plane import DataPlane
    from cell.dataplane.tables import TP

    pin(1)
    rob = [{"id": r, "name": f"b{r}", "skill_port": 20000 + r} for r in range(1, robots + 1)]
    dp = {
        "listen": f"{SWITCH_R}:{STATUS_PORT}",
        "forward": [{"listen": f"{SWITCH_G}:{FORWARD_PORT}", "to": f"{ROBOT_ADDR}:{SINK_PORT}"}],
        "egress": {"rate_mbps": rate_mbps, "buffer_kb": buffer_kb, "scheduling": scheduling},
    }
    plane = DataPlane(load_config(overrides={"robots": rob, "dataplane": dp}))
    # every robot heads for a TP 0.1 rad away, forever (a self-loop): each status takes the full pipeline
    plane.tables.insert([TP(r, 1, 1, 1.0, [0.1] * 6, [0.0] * 6) for r in range(1, robots + 1)])
    for r in range(1, robots + 1):
        plane.tables.set_registers(r, 1, 2**62)

    async def main() -> None:
        stop = asyncio.Event()
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
        print("ready", flush=True)
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(plane.run()), tg.create_task(plane.pump())]
            await stop.wait()
            for t in tasks:
                t.cancel()

    try:
        asyncio.run(main())
    finally:
        plane.close()
    print(json.dumps(plane.counters()), flush=True)


def gen_main(frame: int, mbps: float, seconds: float) -> None:
    """Ordinary traffic: `frame`-byte frames at `mbps` to the switch's forwarding port, each as soon
    as BURST_BYTES of them are due (GSO); prints what it sent as one JSON line."""
    from cell.bench import pin
    from cell.robot import udp

    pin(0)
    seg = frame - HEADERS
    sock = udp.open_socket(GEN_ADDR, gro=False)
    rate = mbps * 1e6 / 8 / frame  # frames/s
    buf = memoryview(bytes(seg * udp.GSO_MAX_SEGMENTS))
    sent = offered = 0
    t0 = time.perf_counter()
    least = max(1, BURST_BYTES // frame)  # frames a send waits for (64-byte frames one by one: no switch
    # of ours keeps up with them; the paper's generator is a NIC)
    while (now := time.perf_counter() - t0) < seconds:  # (busy: as smooth as that allows)
        due = int(now * rate)
        while offered + least <= due:
            k = min(udp.GSO_MAX_SEGMENTS, due - offered)
            sent += udp.send_segments(sock, buf[: k * seg], seg, (SWITCH_G, FORWARD_PORT))
            offered += k
    took = time.perf_counter() - t0
    print(json.dumps({"offered": offered, "sent": sent, "mbps": sent * frame * 8 / took / 1e6}), flush=True)


def robots_main(robots: int, seconds: float) -> None:
    """The robots (cell.bench.dataplane's load at 500 Hz) and the sink of ordinary traffic."""
    from cell.bench import pin
    from cell.bench.dataplane import _load
    from cell.robot import udp

    pin(0)
    with contextlib.suppress(OSError, AttributeError):  # ahead of the generator on this core: robots' time
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
    sink = udp.open_socket(ROBOT_ADDR, SINK_PORT)
    try:
        out = _load((SWITCH_R, STATUS_PORT), robots, seconds, bind=ROBOT_ADDR, sink=sink)
    finally:
        sink.close()
    print(json.dumps(dataclasses.asdict(out)), flush=True)


# --- the experiment -------------------------------------------------------------------------------


def _last_json(text: str) -> dict[str, Any]:
    return json.loads(next(x for x in reversed(text.splitlines()) if x.startswith("{")))


def point(ns: dict[str, str], robots: int, frame: int, bg_mbps: float, seconds: float) -> dict[str, Any]:
    """One load level: the generator runs around the robots' measurement."""
    gen = subprocess.Popen(
        _role(ns["gen"], "gen", str(frame), str(bg_mbps), str(seconds + 2.5)),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(0.5)  # (the generator under way before the robots measure: no synchronisation needed)
        rob = subprocess.run(
            _role(ns["robots"], "robots", str(robots), str(seconds)),
            capture_output=True,
            text=True,
            timeout=seconds + 30,
        )
        g_out, _ = gen.communicate(timeout=seconds + 30)
    finally:
        if gen.poll() is None:
            gen.kill()
    if rob.returncode or gen.returncode:
        raise RuntimeError(f"bench role failed: {rob.stderr[-2000:]}")
    r, g = _last_json(rob.stdout), _last_json(g_out)
    return {
        "robot": r,
        "gen": g,
        "lost_fraction": 1 - r["answered"] / max(r["sent"], 1),
        "sink_mbps": r["sink_datagrams"] * frame * 8 / max(r["span_s"], 1e-9) / 1e6,
    }


def run(
    quick: bool = False,
    rate_mbps: float = 100.0,
    buffer_ms: float = 3.0,
    seconds: float | None = None,
    log: Log = print,
    loads: tuple[float, ...] | None = None,
    frames: tuple[int, ...] = FRAMES,
) -> Result:
    why = available()
    if why:
        raise RuntimeError(f"cell bench background {why}")
    loads = loads or (QUICK_LOADS if quick else LOADS)
    seconds = seconds or (1.0 if quick else 2.0)
    robots = max(1, round(ROBOT_SHARE * rate_mbps * 1e6 / COMMAND_BPS_PER_ROBOT))
    buffer_kb = rate_mbps * 1e6 / 8 * buffer_ms / 1e3 / 1024
    rows: list[Point] = []
    t0 = time.monotonic()
    with namespaces() as ns:
        for scheduling in ("fifo", "priority"):
            sw = subprocess.Popen(
                _role(ns["switch"], "switch", str(robots), str(rate_mbps), str(buffer_kb), scheduling),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            try:
                assert sw.stdout is not None
                if sw.stdout.readline().strip() != "ready":
                    raise RuntimeError(
                        f"the switch did not start: {sw.stderr.read()[-2000:] if sw.stderr else ''}"
                    )
                for frame in frames:
                    for load in loads:
                        bg = max(0.0, load * rate_mbps - robots * COMMAND_BPS_PER_ROBOT / 1e6)
                        p = point(ns, robots, frame, bg, seconds)
                        r = p["robot"]
                        row = Point(
                            scheduling,
                            frame,
                            load,
                            offered_mbps=p["gen"]["mbps"] + robots * COMMAND_BPS_PER_ROBOT / 1e6,
                            forwarded_mbps=p["sink_mbps"],
                            p50_us=r.get("p50_us", float("nan")),
                            p99_us=r.get("p99_us", float("nan")),
                            max_us=r.get("max_us", float("nan")),
                            lost_fraction=p["lost_fraction"],
                            on_time_fraction=r["on_time_fraction"],
                        )
                        rows.append(row)
                        log(
                            f"  {scheduling:8s} {frame:5d} B  load {load:.1f}x: offered "
                            f"{row.offered_mbps:6.1f} Mbit/s, forwarded {row.forwarded_mbps:6.1f}; "
                            "robots "
                            f"p50 {row.p50_us:8.0f} us  p99 {row.p99_us:8.0f} us  lost "
                            f"{100 * row.lost_fraction:5.1f}%"
                        )
            finally:
                sw.send_signal(signal.SIGTERM)
                try:
                    out, err = sw.communicate(timeout=10)
                except subprocess.TimeoutExpired:
                    sw.kill()
                    out, err = sw.communicate()
            if sw.returncode:
                raise RuntimeError(f"the switch failed: {err[-2000:]}")
            counters = _last_json(out)
            log(
                f"  switch ({scheduling}): robot commands dropped at the port "
                f"{counters['egress.robot_dropped']:.0f}, "
                f"ordinary frames dropped {counters['egress.bulk_dropped']:.0f}, longest robot queueing "
                f"{counters['egress.robot_delay_ms_max']:.2f} ms"
            )
    return Result(rate_mbps, buffer_ms, robots, seconds, rows, time.monotonic() - t0)


def summary(result: Result) -> dict[str, Any]:
    """The figures the paper states, ours: at the highest load, per scheduling, the worst over sizes."""
    out: dict[str, Any] = {"rate_mbps": result.rate_mbps, "robots": result.robots}
    top = max(r.load for r in result.rows)
    low = min(r.load for r in result.rows)
    for s in ("fifo", "priority"):
        hi, lo = result.at(s, top), result.at(s, low)
        out[f"{s}_p99_us_at_{top:g}x"] = max(r.p99_us for r in hi)
        out[f"{s}_lost_at_{top:g}x"] = max(r.lost_fraction for r in hi)
        out[f"{s}_p50_us_at_{low:g}x"] = max(r.p50_us for r in lo)
    return out


def format_result(result: Result) -> str:
    lines = [
        f"egress port {result.rate_mbps:g} Mbit/s, buffer {result.buffer_ms:g} ms per queue, "
        f"{result.robots} robots x 6 joints at 500 Hz (10% of the load at 1x), "
        f"{result.seconds:g} s a point"
    ]
    lines.append(
        f"{'scheduling':10s} {'frame':>6s} {'load':>5s} {'offered':>8s} {'fwd':>7s} "
        f"{'p50 us':>8s} {'p99 us':>8s} {'max us':>8s} {'lost %':>7s}"
    )
    lines += [
        f"{r.scheduling:10s} {r.frame:6d} {r.load:5.1f} {r.offered_mbps:8.1f} "
        f"{r.forwarded_mbps:7.1f} {r.p50_us:8.0f} {r.p99_us:8.0f} {r.max_us:8.0f} "
        f"{100 * r.lost_fraction:7.2f}"
        for r in result.rows
    ]
    lines.append(
        "the paper (Appendix C, Fig. 14; 5 Gbit/s port): one FIFO ~3 ms and some (5 Gbit/s) to almost all "
        "(9 Gbit/s) robot packets lost; strict priority sub-millisecond, none lost; ~1 us at low load"
    )
    lines.append(f"took {result.took_s:.0f} s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """The roles, run by the bench in their namespaces (python -m cell.bench.background ROLE ...)."""
    p = argparse.ArgumentParser(prog="cell.bench.background")
    sub = p.add_subparsers(dest="role", required=True)
    s = sub.add_parser("switch")
    s.add_argument("robots", type=int)
    s.add_argument("rate_mbps", type=float)
    s.add_argument("buffer_kb", type=float)
    s.add_argument("scheduling", choices=("fifo", "priority"))
    g = sub.add_parser("gen")
    g.add_argument("frame", type=int)
    g.add_argument("mbps", type=float)
    g.add_argument("seconds", type=float)
    r = sub.add_parser("robots")
    r.add_argument("robots", type=int)
    r.add_argument("seconds", type=float)
    a = p.parse_args(argv)
    if a.role == "switch":
        switch_main(a.robots, a.rate_mbps, a.buffer_kb, a.scheduling)
    elif a.role == "gen":
        gen_main(a.frame, a.mbps, a.seconds)
    else:
        robots_main(a.robots, a.seconds)


if __name__ == "__main__":
    main()


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="three load levels, 1 s each (about 50 s)")
    p.add_argument("--rate-mbps", type=float, default=100.0, help="the egress port's rate (default 100)")
    p.add_argument(
        "--buffer-ms", type=float, default=3.0, help="its buffer per queue, in ms of it (default 3)"
    )
    p.add_argument(
        "--xdp",
        action="store_true",
        help="instead: the XDP pipeline's response time beside ordinary traffic at rising rates, next to "
        "plain forwarding (Sec. 7.1)",
    )


def _main(args: argparse.Namespace) -> Figures:
    if args.xdp:
        from cell.bench import background_xdp
        from cell.config import xdp_missing

        if why := xdp_missing():
            return Figures(Failed(why), f"cell bench background --xdp: {why}", 2)
        s = background_xdp.sweep(args.quick, log=log)
        return Figures(s, background_xdp.format_result(s))
    result = run(args.quick, args.rate_mbps, args.buffer_ms, log=log)
    return Figures(result, format_result(result))


register(
    Bench(
        "background",
        "robot traffic beside ordinary traffic at a congested egress port of the data plane, one shared "
        "FIFO against strict priority, in network namespaces (NSDI'22 Appendix C, Fig. 14; needs root)",
        _arguments,
        _main,
    )
)
