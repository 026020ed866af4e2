"""NSDI'22 Sec. 7.1 on the XDP backend: the robot pipeline's response time while ordinary traffic
of 64- or 1,280-byte frames passes through the same program at rising rates, next to a plain
forwarding program measured the same way in the same run (`cell bench background --xdp`, and
`cell bench paper`'s xdp-background).

The switch is a network namespace joined to the host by a veth pair (cell.dataplane.xdp.switch),
its end's packets processed on core 1 (RPS), as a switch pipeline's.  At each rate a generator on
the host (core 0, nice 19: the probes' load generator goes first) sends the ordinary traffic to a
port of the switch that no program claims: the program passes it (XDP_PASS) to the switch's stack,
which delivers it to a socket nobody reads, dropped there once its buffer is full.  Meanwhile a
probe of ten robots x 6 joints at 500 Hz (cell.bench.dataplane's load, kernel receive stamps) runs
against the velocity-control program with every robot following a TP, then against `reflect`, the
object's plain forwarding program (each probe datagram straight back), the two interleaved over
two or three rounds, each program's figure the median of its rounds.  The paper's figures are a
Tofino's (0.6-1.3 us at 64 B, toward 2 us at 1,280 B, < 0.2 us from plain forwarding); ours are
veth, generic XDP and a user-space prober on two cores: the difference between the two programs is
what compares.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import socket
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cell.bench import pin
from cell.bench.frames import FRAMES, HEADERS

RATES_KPPS = (0, 50, 100, 200)  # ordinary frames offered, thousands a second
QUICK_RATES_KPPS = (0, 50, 100)
PROBE_ROBOTS = 10
SINK_PORT = 7001
PAPER = {
    "p50_64": "0.6-1.3 us (64 B)",
    "p50_1280": "toward 2 us (1,280 B)",
    "apart": "< 0.2 us from plain forwarding",
}


@dataclass
class Point:
    """One frame size and rate: what the generator sent, each program's probe times (us)."""

    frame: int
    kpps: float  # asked for
    offered_kpps: float = 0.0  # sent
    offered_mbps: float = 0.0
    forward_p50_us: float = float("nan")
    forward_p99_us: float = float("nan")
    control_p50_us: float = float("nan")
    control_p99_us: float = float("nan")
    control_on_time: float = 0.0  # probes answered within the command window

    @property
    def apart_us(self) -> float:
        """The velocity-control pipeline's own share: its median minus plain forwarding's."""
        return self.control_p50_us - self.forward_p50_us


@dataclass
class Sweep:
    points: list[Point] = field(default_factory=list)
    seconds: float = 0.0

    def figures(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in FRAMES:
            pts = [p for p in self.points if p.frame == f]
            if pts:
                top = max(pts, key=lambda p: p.kpps)
                out[f"control_p50_us_{f}"] = top.control_p50_us
                out[f"forward_p50_us_{f}"] = top.forward_p50_us
                out[f"control_p99_us_{f}"] = top.control_p99_us
                out[f"forward_p99_us_{f}"] = top.forward_p99_us
                out[f"apart_us_{f}"] = top.apart_us
                out[f"offered_kpps_{f}"] = top.offered_kpps
        return out

    def to_json(self) -> dict[str, Any]:
        """The JSON line: figures() (keys named by frame size, so not fields), then every point with
        its apart_us."""
        rows = [asdict(p) | {"apart_us": p.apart_us} for p in self.points]
        return self.figures() | {"rows": rows}


def _generator(src: str, dst: tuple[str, int], frame: int, kpps: float, out: Any, stop: Any) -> None:
    """Ordinary frames at kpps until stop, in 1 ms bursts (GSO); what went out put on `out`."""
    from cell.robot import udp

    pin(0)
    os.nice(19)
    seg = frame - HEADERS
    sock = udp.open_socket(src, gro=False)
    buf = memoryview(bytes(seg * udp.GSO_MAX_SEGMENTS * 4))
    rate = kpps * 1e3
    sent = offered = 0
    out.put("up")
    t0 = time.perf_counter()
    while not stop.is_set():
        due = int((time.perf_counter() - t0) * rate)
        while offered < due:
            k = min(udp.GSO_MAX_SEGMENTS * 4, due - offered)
            sent += udp.send_segments(sock, buf[: k * seg], seg, dst)
            offered += k
        time.sleep(0.001)
    out.put((sent, time.perf_counter() - t0))
    sock.close()


def sweep(
    quick: bool = False,
    seconds: float | None = None,
    log: Callable[[str], None] = print,
    frames: tuple[int, ...] = FRAMES,
    rates: tuple[float, ...] | None = None,
    rounds: int | None = None,
) -> Sweep:
    """Every frame size and rate (see the module's docstring); SwitchError if XDP cannot run here."""
    from cell.bench.dataplane import Trial, trial
    from cell.bench.xdpnet import xdp_switch
    from cell.dataplane.xdp.switch import in_namespace, switch_namespace

    seconds = seconds or (1.0 if quick else 2.0)
    rates = rates or (QUICK_RATES_KPPS if quick else RATES_KPPS)
    rounds = rounds or (2 if quick else 3)  # each figure: the median of its rounds (this machine is noisy)
    result = Sweep()
    t_start = time.monotonic()
    net = xdp_switch(cpu=1, tag="cbb")
    ctx = mp.get_context("spawn")
    with switch_namespace(net):

        def sink() -> socket.socket:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 16)
            s.bind((net.switch_addr, SINK_PORT))
            return s

        drop = in_namespace(net.netns, sink)  # (never read: what reaches it is dropped once it is full)
        try:
            for frame in frames:
                for kpps in rates:
                    p = Point(frame, kpps)
                    out, stop = ctx.Queue(), ctx.Event()
                    gen = None
                    if kpps > 0:
                        args = (net.host_addr, (net.switch_addr, SINK_PORT), frame, kpps, out, stop)
                        gen = ctx.Process(target=_generator, args=args, daemon=True)
                        gen.start()
                        out.get(timeout=30)  # under way before the probes
                    fwd: list[Trial] = []
                    ctl: list[Trial] = []
                    try:
                        for k in range(rounds):  # interleaved, the order turned each round
                            for name in ("xdp-reflector", "xdp")[:: 1 if k % 2 == 0 else -1]:
                                t = trial(name, PROBE_ROBOTS, seconds, net)
                                (fwd if name == "xdp-reflector" else ctl).append(t)
                    finally:
                        stop.set()
                        if gen is not None:
                            sent, took = out.get(timeout=30)
                            gen.join(10)
                            p.offered_kpps = sent / took / 1e3
                            p.offered_mbps = sent * frame * 8 / took / 1e6
                    p.forward_p50_us = float(np.median([t.p50_us for t in fwd]))
                    p.forward_p99_us = float(np.median([t.p99_us for t in fwd]))
                    p.control_p50_us = float(np.median([t.p50_us for t in ctl]))
                    p.control_p99_us = float(np.median([t.p99_us for t in ctl]))
                    p.control_on_time = min(t.on_time_fraction for t in ctl)
                    result.points.append(p)
                    log(format_point(p))
        finally:
            drop.close()
    result.seconds = time.monotonic() - t_start
    return result


def format_point(p: Point) -> str:
    return (
        f"  {p.frame:5d} B at {p.kpps:5.0f} kpps (sent {p.offered_kpps:6.1f} kpps, "
        f"{p.offered_mbps:7.1f} Mbit/s): "
        f"velocity control p50/p99 {p.control_p50_us:6.0f}/{p.control_p99_us:6.0f} us, plain forwarding "
        f"{p.forward_p50_us:6.0f}/{p.forward_p99_us:6.0f} us, apart {p.apart_us:+.0f} us"
    )


def format_result(s: Sweep) -> str:
    lines = [
        f"Sec. 7.1 on XDP: {PROBE_ROBOTS} robots' probes through the pipeline beside ordinary traffic "
        f"(paper: {PAPER['p50_64']}, {PAPER['p50_1280']}, {PAPER['apart']})",
        *(format_point(p) for p in s.points),
        f"took {s.seconds:.0f} s",
    ]
    return "\n".join(lines)
