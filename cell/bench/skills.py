"""`cell bench skills`: the task-script path's timing, next to the Adept V+ paper's figures.

A cell (bus, data plane, two kinematic robots, controller, skill servers)
runs in a child process; a task script's client runs here, as `cell run`
would.  Measured:

- acknowledgement round trip of `set_speed` (no motion: the skill server
  still asks the controller for the tool pose it reports), p50/p99: the
  paper's tau_r (5.219 ms mean, sd 0.964 ms, on a real Adept robot);
- the gap between consecutive sends of a script (an ack in, the next message
  out): the paper's ~0.2 ms;
- switching: a script alternating a bus request (the controller's pose) and
  a robot request; the time from one's reply to the other's send: the
  paper's ~1 ms.
Baseline in the same run: a bare TCP echo of the same bytes on loopback.
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cell.bench.cellproc import free_port, running_cell
from cell.bus import Bus
from cell.skills.client import RobotClient, SetSpeed
from cell.v1 import controller_pb2


def _stats(ns: list[int]) -> dict[str, float]:
    a = np.array(ns) / 1e6
    return {
        "p50_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "mean_ms": float(a.mean()),
        "sd_ms": float(a.std()),
    }


async def _echo_baseline(n: int) -> list[int]:
    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while line := await reader.readline():
            writer.write(line)

    server = await asyncio.start_server(echo, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    out = []
    for i in range(n):
        t = time.monotonic_ns()
        writer.write(f"{i:08x}:set_speed:50\r\n".encode())
        await reader.readline()
        out.append(time.monotonic_ns() - t)
    writer.close()
    server.close()
    return out


async def measure(n: int, log: Callable[[str], None]) -> dict[str, Any]:
    robots = [{"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "kinematic"} for i in (1, 2)]
    services = ["bus", "dataplane", "robots", "controller", "skills"]
    overrides = {"robots": robots, "services": {"run": services}}
    echo = await _echo_baseline(n)
    async with (
        running_cell(overrides) as config,
        Bus.connect(config.bus, "bench-skills") as bus,
        RobotClient("r1", config.skills.host, robots[0]["skill_port"], bus) as robot,
    ):
        for _ in range(50):  # warm up
            await robot.cmdexec(SetSpeed(50))
        acks = [(await robot.cmdexec(SetSpeed(50)))[0] for _ in range(n)]
        rtt = [a.received_ns - a.sent_ns for a in acks]
        gaps = [b.sent_ns - a.received_ns for a, b in itertools.pairwise(acks)]
        log(f"set_speed round trip: {len(rtt)} messages")
        # switching between the bus and a robot, as a script that asks the cell and moves the robot
        to_robot, to_bus, pose_rtt = [], [], []
        pose_req = controller_pb2.RobotRequest(robot="r1")
        last_ack = None
        for _ in range(n // 2):
            t_bus_sent = time.monotonic_ns()
            if last_ack is not None:
                to_bus.append(t_bus_sent - last_ack.received_ns)
            await bus.request("controller", "pose", pose_req, controller_pb2.PoseReply, 5.0)
            t_bus_reply = time.monotonic_ns()
            pose_rtt.append(t_bus_reply - t_bus_sent)
            (last_ack,) = await robot.cmdexec(SetSpeed(50))
            to_robot.append(last_ack.sent_ns - t_bus_reply)
        log("switching: done")
    return {
        "messages": n,
        "set_speed_rtt": _stats(rtt),
        "tcp_echo_rtt": _stats(echo),
        "send_gap": _stats(gaps),
        "switch_bus_to_robot": _stats(to_robot),
        "switch_robot_to_bus": _stats(to_bus),
        "controller_pose_rtt": _stats(pose_rtt),
    }


def run(n: int = 2000, log: Callable[[str], None] = print) -> dict[str, Any]:
    return asyncio.run(measure(n, log))


def format_result(r: dict[str, Any]) -> str:
    def line(name: str, s: dict[str, float]) -> str:
        figures = (
            f"p50 {s['p50_ms']:6.3f}  p99 {s['p99_ms']:6.3f}  mean {s['mean_ms']:6.3f}  sd {s['sd_ms']:6.3f}"
        )
        return f"  {name:<42} {figures} ms"

    return "\n".join(
        [
            f"{r['messages']} messages; the Adept V+ paper (real robot): tau_r 5.219 ms mean, sd 0.964; "
            "send gaps ~0.2 ms; switching ~1 ms",
            line("set_speed acknowledgement round trip", r["set_speed_rtt"]),
            line("bare TCP echo of the same bytes (baseline)", r["tcp_echo_rtt"]),
            line("gap: an ack in, the next message out", r["send_gap"]),
            line("switch: bus reply in, robot message out", r["switch_bus_to_robot"]),
            line("switch: robot ack in, bus request out", r["switch_robot_to_bus"]),
            line("bus request: the controller's pose", r["controller_pose_rtt"]),
        ]
    )
