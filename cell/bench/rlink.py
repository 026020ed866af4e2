"""`cell bench rlink`: the Responsive Processor paper's Table 1 and Fig. 10 on the software link.

Two nodes in separate processes, A (address 1) measuring and B (address 2)
echoing, wired L1 <-> L2 over loopback, each pinned to a core at SCHED_FIFO
where allowed.  A times the round trip of 10,000 event packets and 10,000
data packets, one at a time (ECHO -> ECHO_REPLY through B's host), then the
same while a third process floods B's data link as fast as it can: the event
link must not notice, the data link does.  Data echoes under load that do
not come back within LOST_S count as lost.  The paper's break-even condition
(1), S_p T_e / M < S_p T_d / D, is evaluated with the times measured here.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import queue
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cell import aio, sched
from cell.bench import estop
from cell.bench.registry import Bench, Figures, register
from cell.jsonfields import OMIT_IF_NONE, JsonFields
from cell.ports import free_port
from cell.rlink.link import LinkPorts, NodeLink
from cell.rlink.node import Node
from cell.rlink.packet import DATA_PAYLOAD, EVENT_PAYLOAD, EventType, Kind, Packet, encode
from cell.rlink.routing import Route, RoutingTable

ECHO, REPLY = int(EventType.ECHO), int(EventType.ECHO_REPLY)  # the same type numbers on the data link
LOST_S = 0.2  # a data echo under load that takes longer is lost (most are: the flood fills the buffers)
WARMUP = 200


def _ports() -> dict[str, tuple[str, int]]:
    return {name: ("127.0.0.1", free_port(socket.SOCK_DGRAM)) for name in ("a_ev", "a_da", "b_ev", "b_da")}


def _table(me: int, link: int) -> RoutingTable:
    return RoutingTable([Route(links=(link,)), Route(links=(0,), dst=me)])


def _echo_node(ports: dict, stop: Any, out: Any) -> None:
    sched.place([1], 50, -10)

    async def main() -> None:
        def echo_event(p: Packet) -> None:
            if p.type == ECHO:
                b.send(Kind.EVENT, p.src, REPLY, p.payload, p.priority)

        def echo_data(batch: list[Packet]) -> None:
            for p in batch:
                if p.type == ECHO:
                    b.send(Kind.DATA, p.src, REPLY, p.payload, p.priority)

        links = [LinkPorts(2, ports["b_ev"], ports["b_da"], ports["a_ev"], ports["a_da"])]
        b = NodeLink(Node(2, _table(2, 2)), links, echo_event, echo_data)
        task = asyncio.create_task(b.run())
        out.put("ready")
        await asyncio.to_thread(stop.wait)  # a multiprocessing event: waited for in a thread
        task.cancel()
        c = b.node.links[2]
        out.put({"data_in": c.packets_in[Kind.DATA], "drops": sum(b.node.drops.values())})
        b.close()

    aio.run(main())


def _bulk(ports: dict, flowing: Any, stop: Any, out: Any) -> None:
    """Data packets from 'node 1' to node 2's data link, as fast as this process can send them;
    `flowing` is set once they do (the measuring node waits for it, not for this process's start)."""
    sched.place([0], 0, 0)
    raw = encode(Packet(Kind.DATA, 2, 1, 0, 1, 0, bytes(DATA_PAYLOAD)))
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    dst, sent, t0 = ports["b_da"], 0, time.monotonic()
    while not stop.is_set():
        for _ in range(256):
            try:
                s.sendto(raw, dst)
                sent += 1
            except OSError:
                pass
        flowing.set()
    took = time.monotonic() - t0
    out.put({"bulk_sent": sent, "bulk_rate": sent / took, "bulk_s": took})


def _measure(ports: dict, n: int, n_loaded_data: int, load_ready: Any, loaded: Any, out: Any) -> None:
    problems = sched.place([0], 60, -10)

    async def main() -> dict[str, Any]:
        waiting: dict[int, asyncio.Future[None]] = {}

        def answered(p: Packet) -> None:
            fut = waiting.pop(int.from_bytes(p.payload[:4], "big"), None)
            if fut is not None and not fut.done():
                fut.set_result(None)

        def answered_all(batch: list[Packet]) -> None:
            for p in batch:
                answered(p)

        links = [LinkPorts(1, ports["a_ev"], ports["a_da"], ports["b_ev"], ports["b_da"])]
        a = NodeLink(Node(1, _table(1, 1)), links, answered, answered_all)
        task = asyncio.create_task(a.run())
        loop = asyncio.get_running_loop()
        token = 0

        async def rtts(kind: Kind, count: int, timeout: float) -> tuple[list[float], int]:
            nonlocal token
            got, lost = [], 0
            for _ in range(count):
                token += 1
                fut = waiting[token] = loop.create_future()
                t0 = time.perf_counter_ns()
                a.send(kind, 2, ECHO, token.to_bytes(4, "big"), priority=3 if kind == Kind.EVENT else 0)
                try:
                    async with asyncio.timeout(timeout):
                        await fut
                    got.append((time.perf_counter_ns() - t0) / 1e3)
                except TimeoutError:
                    waiting.pop(token, None)
                    lost += 1
            return got, lost

        result: dict[str, Any] = {"placement": sched.describe(), "placement_problems": problems}
        for kind in (Kind.EVENT, Kind.DATA):
            await rtts(kind, WARMUP, 1.0)
            result[f"{kind.name.lower()}_unloaded"] = await rtts(kind, n, 1.0)
        load_ready.set()  # the flood starts
        if not await asyncio.to_thread(loaded.wait, 60):
            raise RuntimeError("the flood on the data link never started")
        await asyncio.sleep(0.3)  # until B's queues are full
        for kind in (Kind.EVENT, Kind.DATA):
            count = n if kind == Kind.EVENT else n_loaded_data
            result[f"{kind.name.lower()}_loaded"] = await rtts(kind, count, LOST_S)
        task.cancel()
        a.close()
        return result

    out.put(aio.run(main()))


@dataclass
class Rtt(JsonFields):
    """One figure's round trips (us), and the echoes that did not come back."""

    n: int
    mean: float
    std: float
    p50: float
    p99: float
    max: float
    lost: int


@dataclass
class EchoNode(JsonFields):
    """What the flooded node took in, and dropped."""

    data_in: int
    drops: int


@dataclass
class BreakEven(JsonFields):
    """The paper's condition (1): an event keeps the shorter latency while S_p T_e / M < S_p T_d / D."""

    T_e_us: float
    M_bytes: int
    T_d_us: float
    D_bytes: int
    event_us_per_byte: float
    data_us_per_byte: float
    holds: bool


@dataclass
class RlinkResult(JsonFields):
    """Table 1's figures, unloaded and with the data link flooded, the e-stop's (cell.bench.estop's,
    without its samples) and the break-even condition; the keys the issue names among them."""

    packets: int
    bulk_sent: int
    bulk_rate: float
    bulk_s: float
    echo_node: EchoNode
    placement: str
    data_handled_per_s: float | None
    event_unloaded: Rtt
    data_unloaded: Rtt
    event_loaded: Rtt
    data_loaded: Rtt
    event_rtt_us_mean: float
    event_rtt_us_std: float
    data_rtt_us_mean: float
    data_rtt_us_std: float
    event_p99_loaded_over_unloaded: float
    estop: dict[str, Any] | None = field(metadata=OMIT_IF_NONE)
    estop_p99_ms: float | None
    break_even: BreakEven
    histogram_png: str | None = field(default=None, metadata=OMIT_IF_NONE)


def _stats(us: list[float], lost: int) -> Rtt:
    a = np.array(us) if us else np.array([np.nan])
    return Rtt(
        n=len(us),
        mean=float(a.mean()),
        std=float(a.std()),
        p50=float(np.percentile(a, 50)),
        p99=float(np.percentile(a, 99)),
        max=float(a.max()),
        lost=lost,
    )


def run(
    n: int = 10_000,
    png: str | None = None,
    n_loaded_data: int = 100,
    estop_trials: int = 300,
    estop_robots: int = estop.FLOOD_ROBOTS,
) -> RlinkResult:
    """The figures; samples are drawn into `png` (if given) and left out of the result.  Then the
    e-stop's end-to-end latency with the data plane loaded (cell.bench.estop); 0 trials: skipped."""
    ctx = mp.get_context("spawn")
    ports = _ports()
    out_b, out_a, out_c = ctx.Queue(), ctx.Queue(), ctx.Queue()
    stop_b, stop_c, load_ready, loaded = ctx.Event(), ctx.Event(), ctx.Event(), ctx.Event()
    b = ctx.Process(target=_echo_node, args=(ports, stop_b, out_b), daemon=True)
    b.start()
    assert out_b.get(timeout=30) == "ready"
    a = ctx.Process(target=_measure, args=(ports, n, n_loaded_data, load_ready, loaded, out_a), daemon=True)
    a.start()
    c = None
    try:
        if not load_ready.wait(timeout=600):
            raise RuntimeError("the unloaded measurements did not finish")
        c = ctx.Process(target=_bulk, args=(ports, loaded, stop_c, out_c), daemon=True)
        c.start()
        m = out_a.get(timeout=600)
    except queue.Empty:
        raise RuntimeError("the measuring node gave no result") from None
    finally:
        stop_c.set()
        stop_b.set()
    bulk = out_c.get(timeout=30)  # (the flood ran: without it there is no result above)
    echo = out_b.get(timeout=30)
    for p in (a, b, c):
        if p is not None:
            p.join(10)
    samples = {}
    rtt = {}
    for key in ("event_unloaded", "data_unloaded", "event_loaded", "data_loaded"):
        got, lost = m[key]
        rtt[key] = _stats(got, lost)
        samples[key] = got
    ev, da = rtt["event_unloaded"], rtt["data_unloaded"]
    e: dict[str, Any] | None = None
    if estop_trials:
        e = estop.run(estop_trials, estop_robots)
        samples["estop"] = e.pop("samples_ms")
    # break-even condition (1): an event keeps the shorter latency while S_p T_e / M < S_p T_d / D
    mailbox, threshold = EVENT_PAYLOAD, DATA_PAYLOAD  # bytes handed over per event / per data hand-over
    r = RlinkResult(
        packets=n,
        bulk_sent=bulk["bulk_sent"],
        bulk_rate=bulk["bulk_rate"],
        bulk_s=bulk["bulk_s"],
        echo_node=EchoNode(**echo),
        placement=m["placement"],
        # what the flooded node still took in (the data echoes of the unloaded phase are a rounding error)
        data_handled_per_s=echo["data_in"] / bulk["bulk_s"] if bulk["bulk_s"] else None,
        event_unloaded=ev,
        data_unloaded=da,
        event_loaded=rtt["event_loaded"],
        data_loaded=rtt["data_loaded"],
        # the JSON keys the issue names
        event_rtt_us_mean=ev.mean,
        event_rtt_us_std=ev.std,
        data_rtt_us_mean=da.mean,
        data_rtt_us_std=da.std,
        event_p99_loaded_over_unloaded=rtt["event_loaded"].p99 / ev.p99,
        estop=e,
        estop_p99_ms=e["estop_p99_ms"] if e is not None else None,
        break_even=BreakEven(
            T_e_us=ev.mean,
            M_bytes=mailbox,
            T_d_us=da.mean,
            D_bytes=threshold,
            event_us_per_byte=ev.mean / mailbox,
            data_us_per_byte=da.mean / threshold,
            holds=ev.mean / mailbox < da.mean / threshold,
        ),
    )
    if png:
        r.histogram_png = histogram(r, samples, png)
    return r


def histogram(r: RlinkResult, samples: dict[str, list[float]], path: str) -> str:
    """Fig. 10 (a) and (b), and the event link under a data flood, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        (r.event_unloaded, "event_unloaded", "(a) event packet"),
        (r.data_unloaded, "data_unloaded", "(b) data packet"),
        (r.event_loaded, "event_loaded", "(c) event packet, data link flooded"),
    ]
    with_estop = r.estop is not None and bool(samples.get("estop"))
    fig, axes = plt.subplots(1, 3 + with_estop, figsize=(13 + 4 * with_estop, 3.6), constrained_layout=True)
    for ax, (s, key, title) in zip(axes, panels, strict=False):
        us = np.array(samples[key])
        if us.size:
            hi = float(np.percentile(us, 99.5))
            ax.hist(us[us <= hi], bins=60, color="#3a78c2")
        ax.set_title(f"{title}\nmean {s.mean:.0f} us, sd {s.std:.0f}, p99 {s.p99:.0f}", fontsize=9)
        ax.set_xlabel("round-trip time (us)")
        ax.set_ylabel("count")
    if with_estop and r.estop is not None:
        ax, e = axes[3], r.estop
        us = np.array(samples["estop"]) * 1e3
        ax.hist(us[us <= np.percentile(us, 99.5)], bins=60, color="#c2453a")
        ax.set_title(
            f"(d) e-stop: order -> first stop command\n"
            f"(data plane {e['plane_handled_per_s'] / 1e6:.2f}M status/s) "
            f"mean {e['estop_ms_mean'] * 1e3:.0f} us, p99 {e['estop_p99_ms'] * 1e3:.0f}",
            fontsize=9,
        )
        ax.set_xlabel("latency (us)")
        ax.set_ylabel("count")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(Path(path).resolve())


def format_result(r: RlinkResult) -> str:
    def line(name: str, s: Rtt) -> str:
        lost = f", {s.lost} lost (> {LOST_S:.1f} s)" if s.lost else ""
        return (
            f"  {name:<34} mean {s.mean:8.1f} us  sd {s.std:7.1f}  p50 {s.p50:7.1f}  "
            f"p99 {s.p99:8.1f}  ({s.n:,}{lost})"
        )

    be = r.break_even
    lines = [
        f"round trips between two nodes in separate processes ({r.placement} for the measuring one):",
        line("event packets", r.event_unloaded),
        line("data packets", r.data_unloaded),
        f"with the data link flooded ({r.bulk_rate:,.0f} packets/s offered, "
        f"{r.data_handled_per_s or 0:,.0f}/s handled by the echo node):",
        line("event packets", r.event_loaded),
        line("data packets", r.data_loaded),
        f"event p99 flooded / unloaded: {r.event_p99_loaded_over_unloaded:.2f} (aim <= 1.2)",
        "paper (Table 1): event 247.8 us mean, sd 6.4; data 663.3 us, sd 20.9",
        f"break-even (1): T_e/M = {be.T_e_us:.1f}/{be.M_bytes} = {be.event_us_per_byte:.2f} us/byte "
        f"{'<' if be.holds else '>='} T_d/D = {be.T_d_us:.1f}/{be.D_bytes} = "
        f"{be.data_us_per_byte:.2f} us/byte: "
        + ("events are the cheaper way per byte too" if be.holds else "per byte, data packets win"),
    ]
    if r.estop:
        e = r.estop
        lines += [
            f"e-stop, order at the hub -> first stop command at the robot, the data plane answering "
            f"{e['plane_handled_per_s']:,.0f} status/s:",
            f"  mean {e['estop_ms_mean']:.2f} ms  p50 {e['estop_ms_p50']:.2f}  p99 {e['estop_p99_ms']:.2f} "
            f"(aim <= 2)  max {e['estop_ms_max']:.2f}  ({e['trials']} trials, {e['missed']} missed); "
            f"in the data plane, event read -> commands sent: p99 {e['plane_stop_us_p99'] or 0:.0f} us",
        ]
    if r.histogram_png:
        lines.append(f"histogram: {r.histogram_png}")
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--packets", type=int, default=10_000, help="round trips per figure (default 10000)")
    p.add_argument("--png", metavar="PATH", help="the histogram (default runs/rlink-<time>.png)")
    p.add_argument("--estop-trials", type=int, default=300, help="e-stops timed (default 300; 0: none)")
    p.add_argument(
        "--estop-robots",
        type=int,
        default=333,
        help="robots (x 6 joints x 500 Hz) loading the data plane meanwhile (default 333: 1M status/s)",
    )


def _main(args: argparse.Namespace) -> Figures:
    png = args.png or f"runs/rlink-{time.strftime('%Y%m%d-%H%M%S')}.png"
    result = run(args.packets, png=png, estop_trials=args.estop_trials, estop_robots=args.estop_robots)
    return Figures(result, format_result(result))


register(
    Bench(
        "rlink",
        "Responsive Link: event and data round trips between two nodes, unloaded and with the data "
        "link flooded (Table 1, Fig. 10 of the Responsive Processor paper)",
        _arguments,
        _main,
    )
)
