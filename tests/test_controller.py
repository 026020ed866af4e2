"""The industrial controller against a real cell: motions streamed into the data plane, followed by
emulated robots, measured from the robots' ground truth on the bus."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cell.bus import Bus
from cell.controller.controller import Controller
from cell.v1 import robot_pb2
from tests.conftest import free_port

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def robots(backend: str, n: int = 1) -> list[dict]:
    return [
        {"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": backend} for i in range(1, n + 1)
    ]


class Truth:
    """The robots' ground truth as it arrives (truth/<name>), kept in order."""

    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[int, np.ndarray, np.ndarray]]] = {}

    async def run(self, bus: Bus) -> None:
        sub = await bus.subscribe("truth/")
        async for env in sub:
            msg = env.decode(robot_pb2.RobotTruth)
            name = env.topic.removeprefix("truth/")
            self.samples.setdefault(name, []).append((msg.t_ns, np.array(msg.q), np.array(msg.qd)))

    def last(self, name: str) -> np.ndarray:
        return self.samples[name][-1][1]


def path_error(samples: list[tuple[int, np.ndarray, np.ndarray]], seg) -> float:
    """The largest joint deviation from the plan while the motion runs (rad)."""
    t = np.array([(t_ns - seg.start_ns) / 1e9 for t_ns, _, _ in samples])
    q = np.array([q for _, q, _ in samples])
    inside = (t >= 0) & (t <= seg.motion.duration)
    assert inside.sum() > 10
    plan, _ = seg.motion.sample(t[inside])
    return float(np.abs(q[inside] - plan).max())


async def ready(ctl: Controller, names: list[str]) -> None:
    """Until the data plane has status from every robot (the robots announce and start streaming)."""
    async with asyncio.timeout(10):
        while True:
            st = await ctl.link.state()
            have = {r.robot_id for r in st.robots if r.status_ns}
            if all(ctl.robot_id(n) in have for n in names):
                return
            await asyncio.sleep(0.05)


@pytest.mark.parametrize("backend", ["kinematic", "mujoco"])
async def test_a_joint_move_ends_on_its_goal_and_holds(start_cell, backend: str) -> None:
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=robots(backend))
    async with Bus.connect(cell.config.bus, "controller") as bus, asyncio.TaskGroup() as tg:
        truth = Truth()
        watcher = tg.create_task(truth.run(bus))
        ctl = Controller(bus, cell.config)
        await ready(ctl, ["r1"])
        goal = Q0 + np.array([0.4, -0.3, 0.2, 0.1, -0.2, 0.5])
        result = await ctl.move_joints("r1", goal)
        assert np.allclose(result.q_end, goal)
        assert 0.5 < (result.end_ns - result.start_ns) / 1e9 < 3.0
        seg = ctl.tracks[1].segment
        assert seg is not None
        err = path_error(truth.samples["r1"], seg)
        assert err < 0.01, f"off the plan by {err * 1000:.1f} mrad"  # measured 2-5 mrad
        async with asyncio.timeout(8):  # the P term closes the last gap on the final hold TP
            while np.abs(truth.last("r1") - goal).max() > 1e-5:
                await asyncio.sleep(0.1)
        st = await ctl.dp.state()
        assert st.loaded == 1  # only the final hold stays loaded
        watcher.cancel()
