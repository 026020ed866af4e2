"""The default cell's main job (`make demo`, `cell demo`): the product end to end, in about a minute.

On the embedded two-robot cell, recorded to runs/<timestamp>.rrd:
1. r1 and r2 start one motion at the same instant (a shared start time);
2. both do pick-and-place style moves through their skill servers at once;
3. r1 is switched onto another trajectory on the fly (TrajectorySwitcher);
4. r2 is stopped (protective stop) in the middle of a motion, then resumes;
5. a few SnP time-bounded queries about where the robots are and will be;
then a summary: moves done, path and stop accuracy, the data plane's figures,
packets, drops, denials.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any

import numpy as np

from cell import sched
from cell.bench.accuracy import SETTLE_S  # (the stop error is read as the bench reads it)
from cell.config import RobotConfig
from cell.layout import process_for
from cell.robot.arm import arm_model
from cell.robot.truth import Truth
from cell.skills.client import DisableAir, EnableAir, MoveJoints, MoveRelWorld, MoveToolZ, SetSpeed
from cell.snp.client import DeadlineMissed, QueryDenied, SnpClient
from cell.snp.packet import Quantity, item_id
from cell.status import rt_holds
from cell.v1 import controller_pb2, health_pb2

HOME = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]  # deg
M = controller_pb2.MoveRequest


class Watch:
    """Ground truth (cell.robot.truth) and plans as they come, for the accuracy figures."""

    def __init__(self, robots: list[RobotConfig]) -> None:
        self.names = {r.id: r.name for r in robots}
        self.models = {r.id: r.model for r in robots}  # (each robot's tool is its own model's)
        self.truth = Truth()
        self.plans: list[tuple[int, np.ndarray, np.ndarray]] = []

    async def run(self, cell: Any) -> None:
        sub = await cell.bus.subscribe("plan/")
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self.truth.run(cell.bus))
            async for env in sub:
                p = env.decode(controller_pb2.Plan)
                self.plans.append((p.robot_id, np.array(p.t_ns), np.array(p.positions).reshape(-1, p.joints)))

    def path_errors(self) -> list[tuple[float, str, int, int, int]]:
        """The tool's distance from the plan at each planned point's time: (mm, robot, which of the
        run's plans (1-based), which TP of it, its TPs); a plan counts only until the robot's next
        plan (a switch or a stop replaces the rest of it)."""
        out = []
        for k, (rid, t, q) in enumerate(self.plans):
            arm = arm_model(self.models[rid])
            later = [p[1][0] for p in self.plans[k + 1 :] if p[0] == rid]
            until = min(later) if later else np.inf
            ts = self.truth.t.get(self.names[rid], [])
            if len(ts) < 2:
                continue
            # the first point is where the motion started; the truth must cover the others' times
            inside = (t > t[0]) & (t >= ts[0]) & (t <= min(ts[-1], until))
            real = self.truth.at(self.names[rid], t[inside])
            for i, a, b in zip(np.flatnonzero(inside), real, q[inside], strict=True):
                mm = float(np.linalg.norm(arm.fk(a)[0] - arm.fk(b)[0]) * 1000)
                out.append((mm, self.names[rid], k + 1, int(i), len(t)))
        return out


MISSED_AIM = 0.001  # of the robots' status periods
LATENESS_AIM_US = 500.0  # p99 of how late a tick starts
STEAL_NOTE = 0.01  # a hypervisor's share of the packet path's CPU worth naming in a run not real time
PATH_AIM_MM = 1.0  # the tool path error's aim at every TP (issue 37: what the bench reaches)
STOP_AIM_RAD = 1e-7  # how close to its goal a robot at rest stands


def verdict(ok: bool, text: str) -> str:
    """A row's value with its verdict against its aim."""
    return f"{'✓' if ok else '✗'} {text}"


class Steal:
    """The hypervisor's share of the packet path's CPUs over the run (sched.stolen_seconds): on a
    VM, the one hold of a real-time loop that nothing in the guest can prevent or see otherwise."""

    def __init__(self, config: Any) -> None:
        self.cpus = process_for(config, ["robots"]).cpus or sorted(sched.stolen_seconds())
        self.t0, self.before = time.monotonic(), sched.stolen_seconds()

    def worst(self) -> tuple[int, float, float]:
        """The packet path's CPU the hypervisor took most of: (cpu, seconds, share of the run)."""
        since, took = sched.stolen_since(self.before), time.monotonic() - self.t0
        stolen = [(since[c], c) for c in self.cpus if c in since]
        if not stolen:
            return -1, float("nan"), float("nan")
        s, cpu = max(stolen)
        return cpu, s, s / max(took, 1e-9)


def real_time_rows(
    status: health_pb2.CellStatus, rb: dict[str, float], steal: tuple[int, float, float] = (-1, 0.0, 0.0)
) -> list[tuple[str, str]]:
    """Whether the robots kept their 2 ms ticks (the ground truth of every figure above), and
    what each service cost: said plainly when the run was not real time, and whether the
    hypervisor took the packet path's CPU meanwhile (steal: cpu, seconds, share)."""
    ticks, missed, late = rb.get("ticks", 0.0), rb.get("missed_ticks", 0.0), rb.get("late_sends", 0.0)
    periods = ticks + missed
    share = missed / periods if periods else 1.0
    p50, p99 = rb.get("lateness_p50_us", float("nan")), rb.get("lateness_p99_us", float("nan"))
    real_time = share < MISSED_AIM and p99 < LATENESS_AIM_US
    if real_time:
        said = f"yes (aims: < {MISSED_AIM:.1%} of ticks missed, lateness p99 < {LATENESS_AIM_US:.0f} us)"
    else:
        said = (
            f"NO: {share:.2%} of ticks missed, lateness p99 {p99:.0f} us (aims < {MISSED_AIM:.1%}, "
            f"< {LATENESS_AIM_US:.0f} us): the robots fell behind, so the figures above are degraded"
        )
        if steal[2] >= STEAL_NOTE:
            cpu, share = steal[0], steal[2]
            said += f"; the hypervisor took {share:.1%} of CPU {cpu} meanwhile (steal: the host's doing)"
    # ground truth is read out of the tick's ring at Python's pace: behind by more than the ring, ticks
    # are lost to every reader (the bag's joint states too); and the bus may lose what it carries
    overruns = rb.get("ring_overruns", 0.0)
    bus_lost = sum(s.last.counters.get("bus.lost", 0.0) for s in status.services)
    places = {s.last.process: s.last.sched for s in status.services if s.last.process}
    loads = sorted(
        (
            (s.name, 1e3 * s.last.counters.get("busy_s", 0.0) / max(s.last.uptime_s, 1e-9))
            for s in status.services
        ),
        key=lambda x: -x[1],
    )
    return [
        ("robot ticks missed / late sends", f"{missed:,.0f} of {periods:,.0f} ({share:.2%}) / {late:,.0f}"),
        ("tick lateness p50 / p99 / max", f"{p50:.0f} / {p99:.0f} / {rb.get('lateness_max_us', 0):.0f} us"),
        ("ticks lost to Python (ring overruns) / bus messages lost", f"{overruns:,.0f} / {bus_lost:,.0f}"),
        ("real time", verdict(real_time, said)),
        ("RT holds", _holds_row(status)),
        (
            "hypervisor steal, packet path's CPU",
            f"CPU {steal[0]}: {steal[1] * 1e3:.0f} ms ({steal[2]:.2%} of the run)" if steal[0] >= 0 else "-",
        ),
        (f"processes ({status.mode})", "; ".join(f"{p}: {w}" for p, w in places.items())),
        ("event-loop time per service, mean", ", ".join(f"{n} {v:.0f}" for n, v in loads) + " ms/s"),
    ]


def _holds_row(status: health_pb2.CellStatus) -> str:
    said = rt_holds(status)
    if said is None:
        return "not watched (no process ran at a real-time priority)"
    return said.removeprefix("RT holds: ") or "none (no real-time process was held runnable but not run)"


async def settled_error(truth: Truth, names: tuple[str, ...], goal: np.ndarray, deadline: float) -> float:
    """The largest joint's distance from goal (rad) over the robots, from their latest ground truth:
    as soon as it is within STOP_AIM_RAD, else at the deadline (time.monotonic())."""
    while True:
        error = max(float(np.abs(np.asarray(truth.q[n][-1]) - goal).max()) for n in names if truth.q.get(n))
        if error <= STOP_AIM_RAD or time.monotonic() >= deadline:
            return error
        await asyncio.sleep(0.05)


async def ask(cell: Any, method: str, req: Any, reply_type: Any, timeout: float = 60.0) -> Any:
    """A request to the controller service."""
    return await cell.request("controller", method, req, reply_type, timeout)


async def main(cell: Any) -> None:
    t0 = time.monotonic()
    steal = Steal(cell.config)
    watch = Watch(cell.config.robots)
    watcher = asyncio.create_task(watch.run(cell))
    await asyncio.sleep(0.2)
    r1, r2 = cell.robot("r1"), cell.robot("r2")
    moves = 0

    def count(acks: list) -> None:
        nonlocal moves
        moves += sum(1 for a in acks if a.skill.startswith("move"))

    print("1. r1 and r2 start together (one start time for both)")
    out = [HOME[0] + 25.0, HOME[1] - 10.0, HOME[2] + 10.0, *HOME[3:]]
    await cell.move_together({"r1": out, "r2": out}, speed=70)
    await cell.move_together({"r1": HOME, "r2": HOME}, speed=70)
    moves += 4

    print("2. pick and place through the skill servers, both robots at once")

    async def pick_place(robot: Any, dx: float) -> list:
        acks = await robot.cmdexec(SetSpeed(80), MoveRelWorld(x=dx))
        acks += await robot.cmdexec(MoveToolZ(50.0), EnableAir(), MoveToolZ(-50.0))
        acks += await robot.cmdexec(SetSpeed(80), MoveRelWorld(y=80.0))
        acks += await robot.cmdexec(MoveToolZ(50.0), DisableAir(), MoveToolZ(-50.0))
        acks += await robot.cmdexec(MoveJoints(joints=tuple(HOME)))
        return acks

    for acks in await asyncio.gather(pick_place(r1, 80.0), pick_place(r2, -80.0)):
        count(acks)

    print("3. r1 switches to another trajectory on the fly")
    far = [HOME[0] + 60.0, HOME[1] - 20.0, HOME[2] + 20.0, *HOME[3:]]
    new = [HOME[0] - 30.0, HOME[1] - 10.0, HOME[2] + 15.0, *HOME[3:]]
    far_req = M(robot="r1", values=np.radians(far).tolist(), speed=40)
    first = asyncio.create_task(ask(cell, "move", far_req, controller_pb2.MoveReply))
    await asyncio.sleep(1.0)
    await ask(
        cell, "replan", M(robot="r1", values=np.radians(new).tolist(), speed=60), controller_pb2.MoveReply
    )
    with contextlib.suppress(Exception):  # the first motion's caller learns it was replaced
        await first
    moves += 2

    print("4. r2 is stopped in the middle of a motion, then resumes it")
    long = [HOME[0] - 60.0, HOME[1] - 15.0, HOME[2] + 20.0, *HOME[3:]]
    moving = asyncio.create_task(r2.cmdexec(SetSpeed(30), MoveJoints(joints=tuple(long))))
    await asyncio.sleep(1.5)
    t_stop = time.monotonic_ns()
    stopped = await ask(cell, "stop", controller_pb2.StopRequest(robots=["r2"]), controller_pb2.StopReply)
    stop_latency_ms = (stopped.t_ns - t_stop) / 1e6  # the data plane's clock is this host's monotonic
    with contextlib.suppress(Exception):
        await moving  # its break is answered with an error: the robot was stopped
    await asyncio.sleep(0.5)
    await ask(cell, "resume", controller_pb2.RobotRequest(robot="r2"), controller_pb2.MoveReply)
    moves += 2
    for acks in await asyncio.gather(*(r.cmdexec(MoveJoints(joints=tuple(HOME))) for r in (r1, r2))):
        count(acks)
    moves_end = time.monotonic()

    print("5. SnP time-bounded queries")
    host, port = cell.config.snp.listen.rsplit(":", 1)
    answered = denied = missed = 0
    async with SnpClient((host, int(port))) as snp:
        await snp.sync_time()
        for _ in range(20):
            for rid in (1, 2):
                pos = item_id(rid, Quantity.POSITION, 0)
                now = snp.now()
                try:
                    await snp.query([(pos, now), (pos, now + 50_000_000)], deadline=now + 5_000_000)
                    answered += 1
                except QueryDenied:
                    denied += 1
                except DeadlineMissed:
                    missed += 1
        try:  # one that is denied: an item no robot has
            await snp.query([(item_id(9, Quantity.POSITION, 0), snp.now())])
        except QueryDenied:
            denied += 1
        except DeadlineMissed:  # (a busy machine: counted, as above, not fatal)
            missed += 1

    # how close each robot comes to rest on its goal, read from the arms' ground truth as the bench
    # reads it: once both are within the aim, or SETTLE_S after the last move (the SnP queries ran
    # in between); the P term closes the last of the gap at c2 (2/s: 1e-5 rad to 1e-7 in 2.3 s)
    stop_error = await settled_error(watch.truth, ("r1", "r2"), np.radians(HOME), moves_end + SETTLE_S)
    watcher.cancel()
    status = await cell.request("cell", "status", health_pb2.StatusRequest(), health_pb2.CellStatus, 5)
    counters = {s.name: dict(s.last.counters) for s in status.services}
    dp, rb = counters.get("dataplane", {}), counters.get("robots", {})
    backend = cell.config.dataplane.chosen()[0]

    def c(key: str) -> float:
        return dp.get(key, 0.0)

    errors = watch.path_errors()
    path = np.array([e[0] for e in errors])
    if path.size:
        _, robot, plan, tp, tps = max(errors)
        path_text = verdict(
            path.max() <= PATH_AIM_MM,
            f"{path.max():.2f} / {np.median(path):.2f} mm (aim <= {PATH_AIM_MM:g} mm); worst: {robot}, "
            f"plan {plan} of the run, TP {tp} of {tps}",
        )
    else:
        path_text = "-"
    drops = f"{c('rejected.length'):.0f}, {c('rejected.kind'):.0f}, {c('rejected.joint'):.0f}"
    rows = [
        ("moves done", f"{moves} (one switched on the fly, one stopped and resumed)"),
        ("data plane", "{} ({})".format(*cell.config.dataplane.chosen())),
        ("tool path error at TPs, max / median", path_text),
        (
            "stop error (joints at rest vs goal)",
            verdict(stop_error <= STOP_AIM_RAD, f"{stop_error:.1e} rad (aim <= {STOP_AIM_RAD:.0e})"),
        ),
        ("stop in effect after the request", f"{stop_latency_ms:.1f} ms"),
        (
            ("data plane batch time p50 / p99", f"{c('batch_p50_us'):.0f} / {c('batch_p99_us'):.0f} us")
            if cell.config.dataplane.runs.batched
            else (  # the C packet path answers each burst as it comes: no batches to time
                f"data plane ({backend}) flips / packet path held",
                f"{c(f'{backend}.gates'):.0f} / at most {c(f'{backend}.gate_us_max'):.0f} us a flip, "
                f"{c(f'{backend}.held'):,.0f} statuses answered with their last command meanwhile",
            )
        ),
        ("status packets in / commands out", f"{c('packets_in'):,.0f} / {c('commands_out'):,.0f}"),
        ("drops (length, kind, joint)", verdict(drops == "0, 0, 0", drops)),
        ("TP steps / resubmits / stalls", f"{c('steps'):.0f} / {c('resubmits'):.0f} / {c('stalls'):.0f}"),
        ("SnP queries answered / denied / missed", verdict(missed == 0, f"{answered} / {denied} / {missed}")),
        *real_time_rows(status, rb, steal.worst()),
        ("run time", f"{time.monotonic() - t0:.1f} s"),
    ]
    width = max(len(k) for k, _ in rows)
    print("\nsummary")
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")
