"""The e-stop's end-to-end latency with the data plane saturated: part of `cell bench rlink`.

Three processes, as in the cell: the data plane (the service's DataPlane and
its Responsive Link node, pinned to CPU 1 at SCHED_FIFO where allowed), the
status of `robots` robots that all follow trajectories, 6 joints each at
500 Hz (the default 333 make 1M datagrams/s, near the data plane's saturation
rate on this machine: `cell bench dataplane`; more than it can take and it
drops status, the probe's too), and the measuring process, which holds the link's hub
and plays one more robot, the probe, streaming status at 500 Hz with a
velocity of 1 rad/s and no trajectory (so it is answered 0: hold).

A trial: the hub's host orders ESTOP for the probe; the latency runs until
the probe's socket receives its first stop command (velocity > 0: the
StopRamp of 1 rad/s, not the hold).  Then RESUME, until it is answered 0
again, and a random pause, so that orders fall at every phase of the data
plane's batches.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import queue
import random
import socket
import time
from typing import Any, TypedDict

import numpy as np

from cell import aio, sched
from cell.ports import free_block, free_port
from cell.rlink import events
from cell.rlink.cellnet import BROADCAST, PORTS
from cell.rlink.packet import EventType, Kind
from cell.robot import datagram, udp
from cell.robot.datagram import SCALE

FLOOD_ROBOTS = 333  # x 6 joints x 500 Hz = 1M status datagrams/s
PERIOD_S = 0.002


def _config(robots: int, rlink_port: int, dp_port: int) -> Any:
    from cell.config import load_config

    rob = [{"id": r, "name": f"b{r}", "skill_port": 20000 + r} for r in range(1, robots + 2)]
    return load_config(
        overrides={
            "robots": rob,
            "dataplane": {"listen": f"127.0.0.1:{dp_port}"},
            "rlink": {"port": rlink_port, "beacon_hz": 0.0, "watchdog_s": 0.0},
        }
    )


def _plane(robots: int, rlink_port: int, dp_port: int, out: Any, stop: Any) -> None:
    problems = sched.place([1], 60, -5)
    from cell.dataplane.plane import DataPlane, PlaneNode
    from cell.dataplane.tables import TP

    cfg = _config(robots, rlink_port, dp_port)
    plane = DataPlane(cfg)
    node = PlaneNode(plane, cfg)
    # the flood's robots head for a TP 0.1 rad away, forever: every packet takes the whole pipeline
    plane.tables.insert([TP(r, 1, 1, 1.0, [0.1] * 6, [0.0] * 6) for r in range(1, robots + 1)])
    for r in range(1, robots + 1):
        plane.tables.set_registers(r, 1, 2**62)

    async def main() -> None:
        tasks = [asyncio.ensure_future(plane.run()), asyncio.ensure_future(node.run())]
        out.put("ready")
        await asyncio.to_thread(stop.wait)
        for t in tasks:
            t.cancel()

    aio.run(main())
    ns = sorted(plane.batch_ns) or [0]
    out.put(
        {
            "packets": plane.packets_in,
            "batches": plane.batches,
            "batch_p99_us": ns[int(len(ns) * 0.99)] / 1e3,
            "batch_max_us": ns[-1] / 1e3,
            "stop_us": node.stop_us,
            "placement": sched.describe(),
            "placement_problems": problems,
        }
    )
    plane.close()
    node.close()


def _flood(robots: int, dp_port: int, flowing: Any, stop: Any, out: Any) -> None:
    sched.place([0], 0, 0)
    recs = datagram.empty(robots * 6)
    recs["robot_id"] = np.repeat(np.arange(1, robots + 1), 6)
    recs["joint_id"] = np.tile(np.arange(6), robots)
    raw = recs.view(np.uint8).data
    sock = udp.open_socket("127.0.0.1")
    sender = udp.Sender(sock, datagram.SIZE)
    chunk = 64 * datagram.SIZE
    addr, sent, t0 = ("127.0.0.1", dp_port), 0, time.monotonic()
    deadline = t0
    while not stop.is_set():
        for i in range(0, len(raw), chunk):
            sent += sender.send(raw[i : i + chunk], addr)
        flowing.set()
        deadline += PERIOD_S
        time.sleep(max(0.0, deadline - time.monotonic()))
    took = time.monotonic() - t0
    out.put({"flood_sent_per_s": sent / took, "flood_s": took})
    sock.close()


class _ProbeState(TypedDict):
    seq: int  # of the probe's last status
    want: bool | None  # moving: what the awaited command does
    fut: asyncio.Future[int] | None  # when it came (perf_counter_ns)


def _probe_status(robot: int, seq: int) -> bytes:
    recs = datagram.empty(6)
    recs["robot_id"], recs["joint_id"], recs["seq"] = robot, np.arange(6), seq
    recs["velocity"] = round(1.0 * SCALE)
    return recs.tobytes()


async def _trials(cfg: Any, probe: int, dp_port: int, n: int) -> dict[str, Any]:
    from cell.rlink.hub import Hub

    hub = Hub(cfg)
    link_task = asyncio.ensure_future(hub.link.run())
    sock = udp.open_socket("127.0.0.1", gro=False)
    sender = udp.Sender(sock, datagram.SIZE)  # one datagram per joint, as robots send
    loop = asyncio.get_running_loop()
    dp = ("127.0.0.1", dp_port)
    state: _ProbeState = {"seq": 0, "want": None, "fut": None}

    def on_command() -> None:
        while True:
            try:
                data = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            recs = datagram.view(bytearray(data[: len(data) // datagram.SIZE * datagram.SIZE]))
            recs = recs[recs["robot_id"] == probe]
            if not recs.size:
                continue
            moving = bool((recs["velocity"] > 0).any())
            fut = state["fut"]
            if fut is not None and not fut.done() and moving == state["want"]:
                fut.set_result(time.perf_counter_ns())

    async def stream() -> None:
        while True:
            state["seq"] += 1
            with contextlib.suppress(OSError):
                sender.send(memoryview(_probe_status(probe, state["seq"])), dp)
            await asyncio.sleep(PERIOD_S)

    async def until(moving: bool, timeout: float) -> int:
        fut: asyncio.Future[int] = loop.create_future()
        state["want"], state["fut"] = moving, fut
        async with asyncio.timeout(timeout):
            return await fut

    def order(kind: EventType) -> None:
        payload = events.robot_sets([probe], 1)[0].encode()
        hub.link.send(Kind.EVENT, BROADCAST, kind, payload, priority=3)

    loop.add_reader(sock.fileno(), on_command)
    streaming = asyncio.ensure_future(stream())
    ms, missed = [], 0
    try:
        await until(False, 10.0)  # the data plane knows the probe: it is answered (hold)
        for _ in range(n):
            await asyncio.sleep(random.uniform(0.005, 0.02))
            t0 = time.perf_counter_ns()
            order(EventType.ESTOP)
            try:
                ms.append((await until(True, 0.5) - t0) / 1e6)
            except TimeoutError:
                missed += 1
            order(EventType.RESUME)
            try:
                await until(False, 1.0)
            except TimeoutError:
                missed += 1
    finally:
        streaming.cancel()
        link_task.cancel()
        loop.remove_reader(sock.fileno())
        sock.close()
        hub.close()
    return {"ms": ms, "missed": missed}


def _measure(cfg_args: tuple, n: int, out: Any) -> None:
    problems = sched.place([0], 70, -10)
    cfg = _config(*cfg_args)
    r = aio.run(_trials(cfg, cfg_args[0] + 1, cfg_args[2], n))
    out.put({**r, "placement": sched.describe(), "placement_problems": problems})


def run(trials: int = 200, robots: int = FLOOD_ROBOTS) -> dict[str, Any]:
    """E-stop latency over `trials`, the data plane loaded with `robots` x 6 joints at 500 Hz."""
    ctx = mp.get_context("spawn")
    rlink_port, dp_port = free_block(PORTS), free_port(socket.SOCK_DGRAM)
    out_p, out_f, out_m = ctx.Queue(), ctx.Queue(), ctx.Queue()
    stop_p, stop_f, flowing = ctx.Event(), ctx.Event(), ctx.Event()
    plane = ctx.Process(target=_plane, args=(robots, rlink_port, dp_port, out_p, stop_p), daemon=True)
    plane.start()
    flood = measure = None
    try:
        if out_p.get(timeout=60) != "ready":
            raise RuntimeError("the data plane did not start")
        flood = ctx.Process(target=_flood, args=(robots, dp_port, flowing, stop_f, out_f), daemon=True)
        flood.start()
        if not flowing.wait(30):
            raise RuntimeError("the flood never started")
        measure = ctx.Process(
            target=_measure, args=((robots, rlink_port, dp_port), trials, out_m), daemon=True
        )
        measure.start()
        m = out_m.get(timeout=120 + trials)
    except queue.Empty:
        raise RuntimeError("the e-stop trials gave no result") from None
    finally:
        stop_f.set()
        stop_p.set()
    f = out_f.get(timeout=30)
    p = out_p.get(timeout=30)
    for proc in (plane, flood, measure):
        if proc is not None:
            proc.join(10)
    a = np.array(m["ms"]) if m["ms"] else np.array([np.nan])
    return {
        "trials": trials,
        "missed": m["missed"],
        "estop_ms_mean": float(a.mean()),
        "estop_ms_p50": float(np.percentile(a, 50)),
        "estop_p99_ms": float(np.percentile(a, 99)),
        "estop_ms_max": float(a.max()),
        "plane_handled_per_s": p["packets"] / f["flood_s"],
        "plane_batch_p99_us": p["batch_p99_us"],
        "plane_batch_max_us": p["batch_max_us"],
        "plane_stop_us_p99": float(np.percentile(p["stop_us"], 99)) if p["stop_us"] else None,
        "flood_sent_per_s": f["flood_sent_per_s"],
        "placement": {"plane": p["placement"], "measure": m["placement"]},
        "samples_ms": m["ms"],
    }
