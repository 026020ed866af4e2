"""`cell bench bus`: bus throughput and round trip next to raw pyzmq PUB/SUB, in one run.

Every variant sends the same 64-byte payloads from one process to another:

- raw multipart: send_multipart([topic, payload]), the usual pyzmq PUB/SUB idiom;
- raw 1-frame: send(topic + payload), the fastest raw form (pyzmq's multipart
  calls cost ~10x a single send/recv, so this is the machine's ceiling);
- raw 1-frame via forwarder: the same through the bus forwarder process, i.e.
  what the cell's architecture costs before any of our Python runs;
- bus: protobuf messages in the bus envelope between asyncio nodes, through the
  forwarder, with loss counting: what services actually get.

Raw variants use blocking loops; rounds alternate and the best of each is kept
(the machine is small and noisy).
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import queue
import statistics
import time
from dataclasses import dataclass, replace
from multiprocessing.process import BaseProcess
from typing import Any

import zmq

from cell import aio
from cell.bench.registry import Bench, Figures, register
from cell.bus import Bus, Forwarder, identity
from cell.config import BusConfig, load_config
from cell.jsonfields import JsonFields
from cell.ports import free_port
from cell.v1 import bus_pb2

PAYLOAD = bytes(range(64))
DATA, WARM, PING, PONG = b"bench/data", b"bench/warm", b"bench/ping", b"bench/pong"
IDLE_S = 2.0  # a receiver that hears nothing this long reports what it has


def _endpoint() -> str:
    return f"tcp://127.0.0.1:{free_port()}"


@dataclass(frozen=True)
class Route:
    """How raw sockets meet: directly (receivers bind) or through the bus forwarder (all connect)."""

    pub: str  # senders connect here
    sub: str  # receivers bind (direct) or connect (forwarder) here
    direct: bool
    cell: str = ""  # through the forwarder: the cell its peers say they belong to (cell.bus.identity)

    def _identify(self, sock: zmq.Socket) -> zmq.Socket:
        if not self.direct:  # (the forwarder lets in only nodes that say which cell they are of)
            identity.identify(sock, self.cell)
        return sock

    def attach_receiver(self, sock: zmq.Socket) -> None:
        (sock.bind if self.direct else self._identify(sock).connect)(self.sub)

    def connect_receiver(self, sock: zmq.Socket) -> None:
        """A receiver that connects whichever way (where the far end binds it, direct)."""
        self._identify(sock).connect(self.sub)

    def attach_sender(self, sock: zmq.Socket) -> None:
        self._identify(sock).connect(self.pub)


@dataclass(frozen=True)
class Framing:
    multipart: bool

    def pack(self, topic: bytes) -> Any:
        return [topic, PAYLOAD] if self.multipart else topic + b"\0" + PAYLOAD

    def send(self, sock: zmq.Socket, msg: Any) -> None:
        sock.send_multipart(msg) if self.multipart else sock.send(msg)

    def recv_topic(self, sock: zmq.Socket, flags: int = 0) -> bytes:
        if self.multipart:
            return sock.recv_multipart(flags)[0]
        frame = sock.recv(flags)
        return frame[: frame.find(b"\0")]


# --- child processes (spawned: module-level functions) ----------------------------------------


def _forwarder(cfg: BusConfig, ready: Any, stop: Any) -> None:
    fwd = Forwarder(cfg)
    fwd.start()
    ready.set()
    stop.wait()
    fwd.stop()


def _raw_sink(route: Route, framing: Framing, n: int, out: Any) -> None:
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.RCVHWM, 0)
    route.attach_receiver(sub)
    sub.subscribe(b"bench/")
    out.put("ready")
    count, first, last, warm_seen = 0, 0.0, 0.0, False
    while count < n and sub.poll(int(IDLE_S * 1000)):
        while True:
            try:
                topic = framing.recv_topic(sub, zmq.NOBLOCK)
            except zmq.Again:
                break
            if topic == DATA:
                if count == 0:
                    first = time.perf_counter()
                count += 1
                last = time.perf_counter()
            elif not warm_seen:
                warm_seen = True
                out.put("warm")
    out.put({"received": count, "seconds": last - first, "lost": n - count})
    sub.close(0)
    ctx.term()


def _raw_echo(ping: Route, pong: Route, out: Any) -> None:
    ctx = zmq.Context()
    sub, pub = ctx.socket(zmq.SUB), ctx.socket(zmq.PUB)
    ping.attach_receiver(sub)
    sub.subscribe(PING)
    if pong.direct:
        pub.bind(pong.sub)
    else:
        pong.attach_sender(pub)
    out.put("ready")
    while sub.poll(int(IDLE_S * 1000)):
        frame = sub.recv()
        pub.send(PONG + frame[len(PING) :])
    sub.close(0)
    pub.close(0)
    ctx.term()


def _bus_sink(cfg: BusConfig, n: int, out: Any) -> None:
    async def main() -> None:
        async with Bus.connect(cfg, "bench-sink") as bus:
            sub = await bus.subscribe("bench/data")
            out.put("ready")
            count, first, last = 0, 0.0, 0.0
            while count < n:
                try:
                    batch = await sub.recv_batch(4096, timeout=IDLE_S)
                except TimeoutError:
                    break
                if count == 0:
                    first = time.perf_counter()
                count += len(batch)
                last = time.perf_counter()
            out.put({"received": count, "seconds": last - first, "lost": n - count, "gaps": sub.lost})

    aio.run(main())


def _bus_echo(cfg: BusConfig, out: Any) -> None:
    async def main() -> None:
        async with Bus.connect(cfg, "bench-echo") as bus:

            def echo(req: bus_pb2.BenchPayload) -> bus_pb2.BenchPayload:
                return req

            await bus.serve("bench", {"echo": (bus_pb2.BenchPayload, echo)})
            sub = await bus.subscribe("bench/ping")
            out.put("ready")
            while True:
                try:
                    env = await sub.recv(timeout=IDLE_S)
                except TimeoutError:
                    return
                bus.publish("bench/pong", env.decode(bus_pb2.BenchPayload))

    aio.run(main())


# --- the measurements (this process sends / pings) ---------------------------------------------


def _spawn(target: Any, *args: Any) -> tuple[BaseProcess, Any]:
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, out), daemon=True)
    proc.start()
    assert out.get(timeout=30) == "ready"
    return proc, out


def _rate(result: dict[str, float], n: int, sent_s: float) -> dict[str, float]:
    return {**result, "rate": result["received"] / max(result["seconds"], 1e-9), "send_rate": n / sent_s}


def raw_throughput(route: Route, framing: Framing, n: int) -> dict[str, float]:
    proc, out = _spawn(_raw_sink, route, framing, n)
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.SNDHWM, 0)
    route.attach_sender(pub)
    warm = framing.pack(WARM)
    while True:  # raw PUB/SUB drops until connected: warm up until the sink hears us
        framing.send(pub, warm)
        try:
            if out.get(timeout=0.01) == "warm":
                break
        except queue.Empty:
            continue
    msg = framing.pack(DATA)
    send = pub.send_multipart if framing.multipart else pub.send
    t0 = time.perf_counter()
    for _ in range(n):
        send(msg)
    sent_s = time.perf_counter() - t0
    result = out.get(timeout=120)
    proc.join(5)
    pub.close(0)
    ctx.term()
    return _rate(result, n, sent_s)


def bus_throughput(cfg: BusConfig, n: int) -> dict[str, float]:
    proc, out = _spawn(_bus_sink, cfg, n)

    async def send() -> tuple[float, dict[str, float]]:
        async with Bus.connect(cfg, "bench-source") as bus:
            msg = bus_pb2.BenchPayload(data=PAYLOAD)
            publish = bus.publish
            t0 = time.perf_counter()
            for _ in range(n):
                publish("bench/data", msg)
            took = time.perf_counter() - t0
            # connected until the sink has them all: a node closes its sockets with LINGER 0, which
            # throws away whatever ZeroMQ's I/O thread has not sent yet (lost messages on a slow host)
            return took, await asyncio.to_thread(out.get, True, 120)

    sent_s, result = aio.run(send())
    proc.join(5)
    return _rate(result, n, sent_s)


def _percentiles(samples_ns: list[int]) -> dict[str, float]:
    us = sorted(s / 1000 for s in samples_ns)
    return {
        "p50_us": statistics.median(us),
        "p99_us": us[min(len(us) - 1, int(len(us) * 0.99))],
        "max_us": us[-1],
        "count": len(us),
    }


def raw_round_trip(ping: Route, pong: Route, pings: int) -> dict[str, float]:
    proc, _ = _spawn(_raw_echo, ping, pong)
    ctx = zmq.Context()
    pub, sub = ctx.socket(zmq.PUB), ctx.socket(zmq.SUB)
    ping.attach_sender(pub)
    pong.connect_receiver(sub)
    sub.subscribe(PONG)
    frame = PING + b"\0" + PAYLOAD
    while True:  # warm up until a pong comes back: both directions are connected
        pub.send(frame)
        if sub.poll(10):
            while sub.poll(50):
                sub.recv()
            break
    samples = []
    for _ in range(pings):
        t0 = time.perf_counter_ns()
        pub.send(frame)
        sub.recv()
        samples.append(time.perf_counter_ns() - t0)
    pub.close(0)
    sub.close(0)
    ctx.term()
    _end_echo(proc)
    return _percentiles(samples)


def bus_round_trip(cfg: BusConfig, pings: int) -> dict[str, dict[str, float]]:
    proc, _ = _spawn(_bus_echo, cfg)

    async def ping() -> dict[str, dict[str, float]]:
        async with Bus.connect(cfg, "bench-pinger") as bus:
            sub = await bus.subscribe("bench/pong")
            msg = bus_pb2.BenchPayload(data=PAYLOAD)
            pubsub, rpc = [], []
            for _ in range(pings):
                t0 = time.perf_counter_ns()
                bus.publish("bench/ping", msg)
                await sub.recv(timeout=5)
                pubsub.append(time.perf_counter_ns() - t0)
            for _ in range(pings):
                t0 = time.perf_counter_ns()
                await bus.request("bench", "echo", msg, bus_pb2.BenchPayload, timeout=5)
                rpc.append(time.perf_counter_ns() - t0)
            return {"pubsub": _percentiles(pubsub), "request": _percentiles(rpc)}

    result = aio.run(ping())
    _end_echo(proc)
    return result


def _end_echo(proc: BaseProcess) -> None:
    """An echo has nothing left to give once its pings are answered: ended now, not after IDLE_S
    of silence (which cost each round trip measurement seconds)."""
    proc.terminate()
    proc.join(5)


VARIANTS = ("raw_multipart", "raw_1frame", "raw_1frame_via_forwarder", "bus")
LABELS = {
    "raw_multipart": "raw pyzmq, multipart",
    "raw_1frame": "raw pyzmq, 1 frame",
    "raw_1frame_via_forwarder": "raw 1 frame, forwarder",
    "bus": "bus (protobuf, asyncio)",
    "bus_request_reply": "bus request/reply",
}


@dataclass
class BusResult(JsonFields):
    """The best round of each variant (throughput: received, seconds, lost, rate, send_rate, and the
    bus's gaps; round trip: p50_us, p99_us, max_us, count), and the bus's share of each raw rate."""

    payload_bytes: int
    messages: int
    pings: int
    rounds: int
    throughput: dict[str, dict[str, float]]
    round_trip: dict[str, dict[str, float]]
    bus_share: dict[str, float]
    rates_by_round: dict[str, list[float]]


def run(messages: int = 200_000, pings: int = 2_000, rounds: int = 3) -> BusResult:
    """Alternate every variant `rounds` times; keep the best of each; the bus's share of each raw one."""
    base = load_config().bus
    cfg = replace(base, pub=_endpoint(), sub=_endpoint(), hwm=max(base.hwm, messages * 2))
    via_fwd = Route(cfg.pub, cfg.sub, direct=False, cell=cfg.cell)
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    fwd = ctx.Process(target=_forwarder, args=(cfg, ready, stop), daemon=True)
    fwd.start()
    if not ready.wait(30):
        raise RuntimeError("bench forwarder did not start")
    tp: dict[str, list[dict[str, float]]] = {v: [] for v in VARIANTS}
    rt: dict[str, list[dict[str, float]]] = {v: [] for v in (*VARIANTS[1:], "bus_request_reply")}
    try:
        for _ in range(rounds):
            ep = _endpoint()
            tp["raw_multipart"].append(raw_throughput(Route(ep, ep, True), Framing(True), messages))
            ep = _endpoint()
            tp["raw_1frame"].append(raw_throughput(Route(ep, ep, True), Framing(False), messages))
            tp["raw_1frame_via_forwarder"].append(raw_throughput(via_fwd, Framing(False), messages))
            tp["bus"].append(bus_throughput(cfg, messages))
            a, b = _endpoint(), _endpoint()
            rt["raw_1frame"].append(raw_round_trip(Route(a, a, True), Route(b, b, True), pings))
            rt["raw_1frame_via_forwarder"].append(raw_round_trip(via_fwd, via_fwd, pings))
            bus_rt = bus_round_trip(cfg, pings)
            rt["bus"].append(bus_rt["pubsub"])
            rt["bus_request_reply"].append(bus_rt["request"])
    finally:
        stop.set()
        fwd.join(10)
    best_tp = {v: max(runs, key=lambda r: r["rate"]) for v, runs in tp.items()}
    best_rt = {v: min(runs, key=lambda r: r["p50_us"]) for v, runs in rt.items()}
    bus_rate = best_tp["bus"]["rate"]
    return BusResult(
        payload_bytes=len(PAYLOAD),
        messages=messages,
        pings=pings,
        rounds=rounds,
        throughput=best_tp,
        round_trip=best_rt,
        bus_share={v: bus_rate / best_tp[v]["rate"] for v in VARIANTS[:3]},
        rates_by_round={v: [r["rate"] for r in runs] for v, runs in tp.items()},
    )


def format_result(r: BusResult) -> str:
    lines = [
        f"bus benchmark: {r.payload_bytes}-byte payloads, {r.messages:,} messages and "
        f"{r.pings:,} round trips per round, best of {r.rounds} rounds",
        f"{'':<26}{'msg/s':>12}{'lost':>7}{'bus share':>11}{'rtt p50 us':>12}{'rtt p99 us':>12}",
    ]
    for v in (*VARIANTS, "bus_request_reply"):
        tp, rt = r.throughput.get(v), r.round_trip.get(v)
        share = r.bus_share.get(v)
        lines.append(
            f"{LABELS[v]:<26}"
            + (f"{tp['rate']:>12,.0f}{int(tp['lost']):>7}" if tp else f"{'-':>12}{'-':>7}")
            + (f"{100 * share:>10.0f}%" if share else f"{'':>11}")
            + (f"{rt['p50_us']:>12.1f}{rt['p99_us']:>12.1f}" if rt else f"{'-':>12}{'-':>12}")
        )
    lines.append(
        "rates by round: "
        + "; ".join(f"{v} " + ", ".join(f"{x:,.0f}" for x in xs) for v, xs in r.rates_by_round.items())
    )
    return "\n".join(lines)


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--messages", type=int, default=200_000, help="messages per throughput round")
    p.add_argument("--pings", type=int, default=2_000, help="round trips per latency round")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds of each (best is kept)")


def _main(args: argparse.Namespace) -> Figures:
    result = run(messages=args.messages, pings=args.pings, rounds=args.rounds)
    return Figures(result, format_result(result))


register(
    Bench(
        "bus",
        "bus messages/s and round trip p50/p99 (64-byte payloads) next to raw pyzmq PUB/SUB",
        _arguments,
        _main,
    )
)
