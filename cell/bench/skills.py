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

Then the paper's own experiment, with the camera (service `vision`) in the
cell: the approach phase of `ufloop` (cell.vision.focus) over its sweep,
appr_speed in {5, 25, 50, 75, 100} % and delta_z in {1.5, 2, 2.5} mm, each
iteration a vision request and then SetSpeed + MoveToolZ joined, timed as the
paper defines it (every message carries its own send time):

- tau_r, eq. (1), as its text defines it: "the duration of waiting on the
  client side" less "the duration of the operation on the server side",
  (t_b^rresp - t_ss^rreq) - (t_b^rend - t_ss^rstart), the server's times from
  its replies: what the increment costs beyond the robot's own work.  The
  formula as printed subtracts the break's *start*; here a break starts (its
  turn comes) as soon as the motion has started, so that reading leaves the
  whole motion in, and is reported beside it (tau_r_literal);
- tau(r->v), eq. (2): the break's reply in to the next vision request out;
  tau(v->r), eq. (3): the vision reply in to the set_speed out;
- tau(ss->mrt), eq. (4), and tau(mrt->b), eq. (5): between the sends.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cell.bench.registry import Bench, Figures, log, register
from cell.bus import Bus
from cell.cellproc import running_cell
from cell.jsonfields import OMIT_IF_NONE, JsonFields
from cell.ports import free_port
from cell.skills.client import RobotClient, SetSpeed
from cell.v1 import controller_pb2
from cell.vision import focus
from cell.vision.client import VisionClient


@dataclass
class Stats(JsonFields):
    """One figure's spread, in ms."""

    p50_ms: float
    p99_ms: float
    mean_ms: float
    sd_ms: float


@dataclass
class Approach(JsonFields):
    """ufloop's approach over the paper's sweep: its eqs. (1)-(5)."""

    increments: int
    tau_r: Stats
    tau_r_literal: Stats
    switch_r_to_v: Stats
    switch_v_to_r: Stats
    gap_ss_mrt: Stats
    gap_mrt_b: Stats


@dataclass
class SkillsResult(JsonFields):
    """The task-script path's timing; with the approach (--increments), its figures, PNGs and the
    keys the issue names (left out of the JSON line when it did not run, as ever)."""

    messages: int
    set_speed_rtt: Stats
    tcp_echo_rtt: Stats
    send_gap: Stats
    switch_bus_to_robot: Stats
    switch_robot_to_bus: Stats
    controller_pose_rtt: Stats
    approach: Approach | None = field(default=None, metadata=OMIT_IF_NONE)
    png: dict[str, str] | None = field(default=None, metadata=OMIT_IF_NONE)
    tau_r_ms_mean: float | None = field(default=None, metadata=OMIT_IF_NONE)
    tau_r_ms_sd: float | None = field(default=None, metadata=OMIT_IF_NONE)
    switch_r_to_v_ms_p50: float | None = field(default=None, metadata=OMIT_IF_NONE)
    switch_v_to_r_ms_p50: float | None = field(default=None, metadata=OMIT_IF_NONE)
    gap_ss_mrt_ms_p50: float | None = field(default=None, metadata=OMIT_IF_NONE)
    gap_mrt_b_ms_p50: float | None = field(default=None, metadata=OMIT_IF_NONE)
    set_speed_ack_ms_p50: float = float("nan")


def _stats(ns: Sequence[float]) -> Stats:
    a = np.array(ns) / 1e6
    return Stats(float(np.median(a)), float(np.percentile(a, 99)), float(a.mean()), float(a.std()))


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


async def measure(n: int, log: Callable[[str], None]) -> SkillsResult:
    ports = {i: free_port() for i in (1, 2)}
    robots = [{"id": i, "name": f"r{i}", "skill_port": ports[i], "backend": "kinematic"} for i in (1, 2)]
    services = ["bus", "dataplane", "robots", "controller", "skills"]
    overrides = {"robots": robots, "services": {"run": services}}
    echo = await _echo_baseline(n)
    async with (
        running_cell(overrides) as config,
        Bus.connect(config.bus, "bench-skills") as bus,
        RobotClient("r1", config.skills.host, ports[1], bus) as robot,
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
    set_speed = _stats(rtt)
    return SkillsResult(
        messages=n,
        set_speed_rtt=set_speed,
        tcp_echo_rtt=_stats(echo),
        send_gap=_stats(gaps),
        switch_bus_to_robot=_stats(to_robot),
        switch_robot_to_bus=_stats(to_bus),
        controller_pose_rtt=_stats(pose_rtt),
        set_speed_ack_ms_p50=set_speed.p50_ms,
    )


SPEEDS = (5, 25, 50, 75, 100)  # the paper's appr_speed values, %
DELTAS = (1.5, 2.0, 2.5)  # its delta_z values, mm


async def approach_sweep(
    increments: int, log: Callable[[str], None]
) -> tuple[Approach, dict[str, list[float]], list[tuple[str, int, int]]]:
    """The approach's figures, its samples (ms, for the histograms) and two iterations' requests."""
    """ufloop's approach phase, `increments` iterations per (speed, delta_z), back and forth in front of
    the camera; the paper's timing figures from every iteration."""
    port = free_port()
    robots = [{"id": 1, "name": "r1", "skill_port": port, "backend": "kinematic"}]
    services = ["bus", "dataplane", "robots", "controller", "skills", "vision"]
    overrides = {"robots": robots, "services": {"run": services}}
    tau_r, literal, r2v, v2r, ss_mrt, mrt_b = [], [], [], [], [], []
    gantt: list[tuple[str, int, int]] = []  # (what, sent, answered) of the first iterations, for Fig. 10
    async with (
        running_cell(overrides) as config,
        Bus.connect(config.bus, "bench-ufloop") as bus,
        RobotClient("r1", config.skills.host, port, bus) as rc,
    ):
        vision = VisionClient(bus)
        await focus.init_move(rc)
        last_break = None
        direction = 1.0
        for speed in SPEEDS:
            for dz in DELTAS:
                for _ in range(increments):
                    m = await vision.request()
                    ss, mrt, b = await focus.move_tool_z(rc, speed, direction * dz)
                    waited = b.received_ns - ss.sent_ns
                    tau_r.append(waited - (b.t_end - ss.t_start) * 1e9)
                    literal.append(waited - (b.t_start - ss.t_start) * 1e9)
                    if last_break is not None:
                        r2v.append(m.sent_ns - last_break.received_ns)
                    v2r.append(ss.sent_ns - m.received_ns)
                    ss_mrt.append(mrt.sent_ns - ss.sent_ns)
                    mrt_b.append(b.sent_ns - mrt.sent_ns)
                    last_break = b
                    if len(gantt) < 8:
                        gantt += [("vision", m.sent_ns, m.received_ns)]
                        gantt += [(a.skill, a.sent_ns, a.received_ns) for a in (ss, mrt, b)]
                direction = -direction  # back over the same stretch next time
            log(f"approach sweep: speed {speed}% done")
    approach = Approach(
        increments=len(tau_r),
        tau_r=_stats(tau_r),
        tau_r_literal=_stats(literal),
        switch_r_to_v=_stats(r2v),
        switch_v_to_r=_stats(v2r),
        gap_ss_mrt=_stats(ss_mrt),
        gap_mrt_b=_stats(mrt_b),
    )
    samples_ms = {
        k: (np.array(v) / 1e6).tolist()
        for k, v in (("tau_r", tau_r), ("r2v", r2v), ("v2r", v2r), ("ss_mrt", ss_mrt), ("mrt_b", mrt_b))
    }
    return approach, samples_ms, gantt


def run(
    n: int = 2000, log: Callable[[str], None] = print, increments: int = 4, png_dir: str | None = None
) -> SkillsResult:
    r = asyncio.run(measure(n, log))
    if increments:
        a, samples, gantt = asyncio.run(approach_sweep(increments, log))
        r.approach = a
        if png_dir:
            r.png = figures(samples, gantt, png_dir)
        r.tau_r_ms_mean, r.tau_r_ms_sd = a.tau_r.mean_ms, a.tau_r.sd_ms
        r.switch_r_to_v_ms_p50, r.switch_v_to_r_ms_p50 = a.switch_r_to_v.p50_ms, a.switch_v_to_r.p50_ms
        r.gap_ss_mrt_ms_p50, r.gap_mrt_b_ms_p50 = a.gap_ss_mrt.p50_ms, a.gap_mrt_b.p50_ms
    return r


def figures(samples: dict[str, list[float]], gantt: list[tuple[str, int, int]], out: str) -> dict[str, str]:
    """Figs. 10-13 as PNGs: two iterations as a Gantt chart, and the histograms with min and max marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Path(out).mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, title, keys in (
        ("fig11-tau-r", "travel time of a motion increment, tau_r (eq. 1)", [("tau_r", "tau_r")]),
        ("fig12-switching", "switching robot/vision (eqs. 2, 3)", [("r2v", "r -> v"), ("v2r", "v -> r")]),
        ("fig13-send-gaps", "between sends (eqs. 4, 5)", [("ss_mrt", "ss -> mrt"), ("mrt_b", "mrt -> b")]),
    ):
        fig, axes = plt.subplots(1, len(keys), figsize=(5.5 * len(keys), 3.6), squeeze=False)
        for ax, (key, label) in zip(axes[0], keys, strict=True):
            v = np.array(samples[key])
            ax.hist(v, bins=40, color="tab:blue", alpha=0.8)
            for x in (v.min(), v.max()):
                ax.axvline(x, color="tab:red", lw=1)
            ax.set_title(f"{label}: mean {v.mean():.3f}, sd {v.std():.3f} ms", fontsize=9)
            ax.set_xlabel("ms")
        fig.suptitle(title, fontsize=10)
        fig.tight_layout()
        paths[name] = str(Path(out) / f"{name}.png")
        fig.savefig(paths[name], dpi=110)
        plt.close(fig)
    fig, ax = plt.subplots(figsize=(10, 2.6))
    t0 = min(s for _, s, _ in gantt)
    lanes = ["break", "move_rel_tool", "set_speed", "vision"]
    for what, sent, got in gantt:
        colour = "tab:orange" if what == "vision" else "tab:blue"
        ax.barh(lanes.index(what), (got - sent) / 1e6, left=(sent - t0) / 1e6, color=colour, height=0.6)
    ax.set_yticks(range(len(lanes)), lanes)
    ax.set_xlabel("ms (the task script's clock)")
    ax.set_title("two iterations of ufloop's approach: vision (orange) and robot (blue) requests (Fig. 10)")
    fig.tight_layout()
    paths["fig10-gantt"] = str(Path(out) / "fig10-gantt.png")
    fig.savefig(paths["fig10-gantt"], dpi=110)
    plt.close(fig)
    return paths


def format_result(r: SkillsResult) -> str:
    def line(name: str, s: Stats) -> str:
        figures = f"p50 {s.p50_ms:6.3f}  p99 {s.p99_ms:6.3f}  mean {s.mean_ms:6.3f}  sd {s.sd_ms:6.3f}"
        return f"  {name:<42} {figures} ms"

    return "\n".join(
        [
            f"{r.messages} messages; the Adept V+ paper (real robot): tau_r 5.219 ms mean, sd 0.964; "
            "send gaps ~0.2 ms; switching ~1 ms",
            line("set_speed acknowledgement round trip", r.set_speed_rtt),
            line("bare TCP echo of the same bytes (baseline)", r.tcp_echo_rtt),
            line("gap: an ack in, the next message out", r.send_gap),
            line("switch: bus reply in, robot message out", r.switch_bus_to_robot),
            line("switch: robot ack in, bus request out", r.switch_robot_to_bus),
            line("bus request: the controller's pose", r.controller_pose_rtt),
            *_approach_lines(r, line),
        ]
    )


def _approach_lines(r: SkillsResult, line: Callable[[str, Stats], str]) -> list[str]:
    a = r.approach
    if a is None:
        return []
    out = [
        f"ufloop's approach, {a.increments} increments (speeds {SPEEDS} %, delta_z {DELTAS} mm); "
        "the paper: tau_r 5.219 / 0.964 ms, switching ~1 ms, send gaps ~0.2 ms",
        line("tau_r, eq. (1): client wait - server span", a.tau_r),
        line("  eq. (1) read literally (motion left in)", a.tau_r_literal),
        line("switch robot -> vision, eq. (2)", a.switch_r_to_v),
        line("switch vision -> robot, eq. (3)", a.switch_v_to_r),
        line("send gap set_speed -> move_rel_tool, eq. (4)", a.gap_ss_mrt),
        line("send gap move_rel_tool -> break, eq. (5)", a.gap_mrt_b),
    ]
    if r.png is not None:
        out.append("PNGs: " + ", ".join(r.png.values()))
    return out


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--messages", type=int, default=2000, help="messages per figure (default 2000)")
    p.add_argument(
        "--increments",
        type=int,
        default=4,
        help="ufloop approach increments per (speed, delta_z) of the paper's sweep, with the camera "
        "(default 4; 0: skip)",
    )
    p.add_argument("--out", metavar="DIR", help="where the PNGs go (default runs/skills-<time>)")


def _main(args: argparse.Namespace) -> Figures:
    out = args.out or f"runs/skills-{time.strftime('%Y%m%d-%H%M%S')}"
    result = run(args.messages, log=log, increments=args.increments, png_dir=out)
    return Figures(result, format_result(result))


register(
    Bench(
        "skills",
        "skill-protocol acknowledgement round trip, send gaps and switching, next to TCP echo; the Adept "
        "paper's tau_r, switching and send gaps over ufloop's approach with the camera (Figs. 10-13)",
        _arguments,
        _main,
    )
)
