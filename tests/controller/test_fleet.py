"""A fleet at scale, end to end: a hundred kinematic arms on one shared socket, each moved to a goal of
its own through the data plane by the controller (issue 38; functional: no timing asserted here, the
figures are `cell bench robots` and `cell bench fleet`'s)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cell.bus import Bus
from cell.controller.controller import Controller
from cell.v1 import robot_pb2
from tests.controller.test_controller import Q0, ready

N = 100


@pytest.mark.slow
async def test_a_hundred_arms_on_one_socket_each_reach_their_own_goal(start_cell) -> None:
    arms = [
        {
            "id": i,
            "name": f"f{i}",
            "skill_port": 40000 + i,
            "backend": "kinematic",
            "socket": "shared",
            "truth_hz": 0,
        }
        for i in range(1, N + 1)
    ]
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=arms)  # (the controller: ours)
    rng = np.random.default_rng(38)
    goals = {a["name"]: Q0 + rng.uniform(-0.4, 0.4, 6) for a in arms}
    async with Bus.connect(cell.config.bus, "fleet") as bus, Controller(bus, cell.config) as ctl:
        await ready(ctl, list(goals))
        st = await ctl.link.state()
        assert len({r.robot_id for r in st.robots if r.status_ns}) == N
        # every arm on its own motion, all under way together, their starts spread over a second as
        # a fleet's are (a hundred started in the same instant overload this 2-core machine's cell)

        async def move(k: int, name: str, goal: np.ndarray):
            await asyncio.sleep(k / N)
            return await ctl.move_joints(name, goal, speed=0.8)

        done = await asyncio.gather(*(move(k, n, q) for k, (n, q) in enumerate(goals.items())))
        assert all(np.allclose(d.q_end, goals[n]) for d, n in zip(done, goals, strict=True))
        st = await ctl.link.state()
        at = {r.robot_id: np.array(r.position) for r in st.robots}
        off = {n: float(np.abs(at[ctl.robot_id(n)] - q).max()) for n, q in goals.items()}
        tol = cell.config.controller.goal_tolerance_rad
        assert max(off.values()) <= tol, sorted(off.items(), key=lambda kv: -kv[1])[:5]
        # one socket carried them all: the robots announce one address
        said = [
            await bus.request(f"robot/{n}", "announce", robot_pb2.AnnounceRequest(), robot_pb2.RobotAnnounce)
            for n in ("f1", f"f{N // 2}", f"f{N}")
        ]
        assert len({a.udp_address for a in said}) == 1 and said[0].udp_address
