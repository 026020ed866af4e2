"""The robots' ground truth as it comes over the bus (truth/<name>), kept for measuring against.

For benchmarks and the demo's summary: interpolated joint positions at any
time, and when a robot started to move.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import numpy as np

from cell.bus import Bus
from cell.v1 import robot_pb2


class Truth:
    """Ground truth per robot name, in time order."""

    def __init__(self) -> None:
        self.t: dict[str, list[int]] = {}
        self.q: dict[str, list[np.ndarray]] = {}

    async def run(self, bus: Bus) -> None:
        sub = await bus.subscribe("truth/")
        async for env in sub:
            name = env.topic.removeprefix("truth/")
            msg = env.decode(robot_pb2.RobotTruth)
            ts = self.t.setdefault(name, [])
            if ts and msg.t_ns <= ts[-1]:
                continue
            ts.append(msg.t_ns)
            self.q.setdefault(name, []).append(np.array(msg.q))

    @classmethod
    @contextlib.asynccontextmanager
    async def watching(cls, bus: Bus) -> AsyncIterator[Truth]:
        """A Truth fed from the bus while the block runs (its watch cancelled on the way out)."""
        truth = cls()
        watcher = asyncio.ensure_future(truth.run(bus))
        try:
            yield truth
        finally:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await watcher

    def at(self, name: str, t_ns: np.ndarray) -> np.ndarray:
        """Joint positions at the given times, interpolated between samples."""
        t = np.array(self.t[name], np.float64)
        q = np.array(self.q[name])
        return np.stack([np.interp(t_ns, t, q[:, j]) for j in range(q.shape[1])], axis=1)

    async def until(self, name: str, t_ns: int) -> None:
        while not self.t.get(name) or self.t[name][-1] < t_ns:  # noqa: ASYNC110 (500 Hz anyway)
            await asyncio.sleep(0.02)

    def start_of_motion(self, name: str, after_ns: int, dist: float = 1e-3) -> float:
        """When the robot first got `dist` rad from where it was at after_ns (ns, interpolated)."""
        t = np.array(self.t[name], np.float64)
        q = np.array(self.q[name])
        q0 = self.at(name, np.array([after_ns]))[0]
        d = np.abs(q - q0).max(axis=1)
        i = int(np.flatnonzero((d >= dist) & (t >= after_ns))[0])
        return float(t[i - 1] + (t[i] - t[i - 1]) * (dist - d[i - 1]) / (d[i] - d[i - 1]))
