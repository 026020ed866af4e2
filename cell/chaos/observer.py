"""What a chaos campaign sees of the cell: each robot's truth and reports, the services' events, the
motions' outcomes and the e-stops' (the campaign judges its promises on these)."""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from cell.bus import Bus
from cell.v1 import health_pb2, robot_pb2

REST = 2e-3  # rad/s: a robot whose every joint is slower than this is at rest


@dataclass
class Outcome:
    """What one waiting command (a move and its break) was answered."""

    robot: str
    status: str  # done, stopped, failed, lost (connection), timeout
    text: str
    after_s: float  # from the fault (negative: before it)


@dataclass
class EStop:
    """An e-stop issued during a fault: when, and what each robot reported."""

    t_ns: int
    still_ms: dict[str, float]  # robot -> its report of standing still, ms after the order
    error: str = ""
    # the most the hypervisor took of any CPU from the order to the last report (steal): a stop the
    # host's other guests held back is theirs, not the cell's (a CI run stolen 10-16%: 4 ms over)
    stolen_ms: float = 0.0


@dataclass
class FaultResult:
    name: str
    held: dict[str, bool]
    detail: dict[str, str]
    detect_ms: float | None
    recover_s: float | None
    figures: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(self.held.values())


class Observer:
    """The robots' truth and events, and the services' events, as they come over the bus."""

    def __init__(self, bus: Bus, robots: list[str]) -> None:
        self.bus = bus
        self.truth: dict[str, deque[tuple[int, float, np.ndarray, bool]]] = {
            r: deque(maxlen=20_000) for r in robots
        }
        # truth may arrive out of order: after a heartbeat dropped a stalled connection, the forwarder
        # still drains the old connection's backlog while the new one brings fresh samples; every
        # judgement goes by the samples' own times
        self.newest: dict[str, tuple[int, float, np.ndarray, bool]] = {}
        self.stops: list[tuple[int, str]] = []  # (t_ns, robot) of protective stops
        self.service_events: list[tuple[int, str, int, str]] = []
        self._sampled = asyncio.Event()

    async def sample(self) -> None:
        """Until the next truth sample."""
        self._sampled.clear()
        await self._sampled.wait()

    async def run(self) -> None:
        subs = await asyncio.gather(
            self.bus.subscribe("truth/"),
            self.bus.subscribe("events/robot/"),
            self.bus.subscribe("events/service/"),
        )
        truth, robot_events, service_events = subs

        async def follow_truth() -> None:
            while True:
                for env in await truth.recv_batch():
                    m = env.decode(robot_pb2.RobotTruth)
                    name = env.topic.removeprefix("truth/")
                    if name in self.truth:
                        qd = np.abs(np.array(m.qd)).max() if m.qd else 0.0
                        sample = (m.t_ns, float(qd), np.array(m.q), m.stopped)
                        self.truth[name].append(sample)
                        if m.t_ns >= self.newest.get(name, sample)[0]:
                            self.newest[name] = sample
                self._sampled.set()

        async def follow_robots() -> None:
            RE = robot_pb2.RobotEvent
            async for env in robot_events:
                ev = env.decode(RE)
                if ev.kind == RE.KIND_PROTECTIVE_STOP:
                    self.stops.append((ev.t_ns, ev.name))

        async def follow_services() -> None:
            async for env in service_events:
                ev = env.decode(health_pb2.ServiceEvent)
                self.service_events.append((time.monotonic_ns(), ev.service, ev.kind, ev.text))

        async with asyncio.TaskGroup() as tg:
            for f in (follow_truth, follow_robots, follow_services):
                tg.create_task(f())

    def latest(self, robot: str) -> tuple[int, float, np.ndarray, bool] | None:
        return self.newest.get(robot)

    def between(self, robot: str, t0: int, t1: int) -> list[tuple[int, float, np.ndarray, bool]]:
        """The robot's truth samples in [t0, t1] in the order of their times."""
        return sorted((s for s in self.truth[robot] if t0 <= s[0] <= t1), key=lambda s: s[0])

    def describe(self, robot: str) -> str:
        """What the truth last said of a robot, and how old that is (for a promise that failed)."""
        last = self.latest(robot)
        if last is None:
            return f"{robot}: no truth heard"
        return f"{robot}: truth {(time.monotonic_ns() - last[0]) / 1e6:.0f} ms old, |qd| {last[1]:.4f} rad/s"

    def at_rest(self, robot: str, fresh_ns: int = 200_000_000) -> bool:
        last = self.latest(robot)
        return last is not None and time.monotonic_ns() - last[0] < fresh_ns and last[1] < REST

    def lunge(self, robot: str, t0: int, t1: int) -> tuple[float, float, float]:
        """After the robot first came to rest in [t0, t1]: how far it went from there (rad, the largest
        joint), its fastest joint speed (rad/s), and when that was (s after t0); zeros if it never rested."""
        samples = [(t, qd, q) for t, qd, q, _ in self.between(robot, t0, t1)]
        rested = next((i for i, (_, qd, _) in enumerate(samples) if qd < REST), None)
        if rested is None or rested == len(samples) - 1:
            return 0.0, 0.0, 0.0
        q_rest = samples[rested][2]
        after = samples[rested + 1 :]
        moved = max(float(np.abs(q - q_rest).max()) for _, _, q in after)
        t, qd, _ = max(after, key=lambda s: s[1])
        return moved, qd, (t - t0) / 1e9
