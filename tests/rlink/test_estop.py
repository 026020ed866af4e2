"""The cell's e-stop over the Responsive Link, end to end: skill protocol, CLI, task-script API."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import time

import numpy as np
import pytest

from cell.bus import Bus, BusError
from cell.dataplane.client import DataplaneClient
from cell.launcher import fetch_status
from cell.rlink.client import EventClient
from cell.skills.protocol import Done, Error
from cell.v1 import robot_pb2
from tests.conftest import ROOT, free_port, run_cell
from tests.skills.test_skills_server import Conn

SERVICES = ["bus", "dataplane", "robots", "rlink", "controller", "skills"]
EXAMPLE = ROOT / "examples" / "estop.py"
Q0_DEG = [0.0, -90.0, 90.0, -90.0, -90.0, 0.0]


@pytest.fixture
async def cell(start_cell):
    robots = [
        {"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic"},
        {"id": 2, "name": "r2", "skill_port": free_port(), "backend": "kinematic"},
    ]
    return await start_cell(run=SERVICES, robots=robots)


def joints(deg: list[float]) -> bytes:
    return ",".join(f"{v:.3f}" for v in deg).encode()


async def truth(bus: Bus, name: str, ok=lambda _t: True) -> robot_pb2.RobotTruth:
    """The robot's next ground truth for which ok() holds."""
    sub = await bus.subscribe(f"truth/{name}")
    try:
        async with asyncio.timeout(5):
            async for env in sub:
                t = env.decode(robot_pb2.RobotTruth)
                if ok(t):
                    return t
    finally:
        sub.close()
    raise AssertionError("no truth")


async def counters_until(config, service: str, ok, timeout: float = 5.0) -> dict[str, float]:
    """The service's counters once ok(counters) holds (they come with heartbeats); AssertionError if never."""
    c: dict[str, float] = {}
    async with asyncio.timeout(timeout):
        while True:
            st = await fetch_status(config, timeout=2.0)
            c = dict(next(s for s in st.services if s.name == service).last.counters)
            if ok(c):
                return c
            await asyncio.sleep(0.1)  # polling interval: the loop's condition decides


@pytest.mark.slow
async def test_an_estop_skill_stops_a_moving_robot_and_motions_are_refused_until_resume(cell) -> None:
    config = cell.config
    r1 = await Conn.open(config.robots[0].skill_port)
    async with Bus.connect(config.bus, "test") as bus:
        far = list(Q0_DEG)
        far[0] = 120.0  # about 1.5 s of motion
        await r1.send(b"mv000001:move_joints:" + joints(far) + b"\r\n")
        (started,) = await r1.replies(1)
        assert isinstance(started, Done)
        before = await truth(bus, "r1", lambda t: t.qd[0] > 0.5)  # well under way
        await r1.send(b"es000001:estop\r\n")
        (stopped,) = await r1.replies(1, timeout=5)
        assert isinstance(stopped, Done), stopped
        here = await truth(bus, "r1")
        assert max(abs(v) for v in here.qd) < 1e-3, "answered before standing still"
        q0 = math.degrees(here.q[0])
        assert math.degrees(before.q[0]) <= q0 < 100.0, f"the motion went on to {q0:.1f} deg"
        # a stopped robot refuses motions, the other one does not
        await r1.send(b"mv000002:move_joints:" + joints(Q0_DEG) + b"\r\n")
        (refused,) = await r1.replies(1)
        assert isinstance(refused, Error) and refused.code == "stopped", refused
        later = await truth(bus, "r1")
        assert abs(math.degrees(later.q[0]) - q0) < 0.01, "a stopped robot moved"
        # the stop went over the link: the data plane and the robots counted it
        await counters_until(
            config, "dataplane", lambda c: c.get("rlink.estops", 0) >= 1 and c.get("stop_commands", 0) > 0
        )
        await counters_until(
            config, "robots", lambda c: c.get("rlink.estops", 0) >= 1 and c.get("rlink.stopped") == 1
        )
        # cell status says what each robot is doing, in a table of its own
        from cell.robot.node import ESTOPPED
        from cell.status import format_status

        await counters_until(config, "robots", lambda c: c.get("robot.r1.state") == ESTOPPED)
        table = format_status(await fetch_status(config, timeout=2.0), counters=False).splitlines()
        robots = table[next(i for i, line in enumerate(table) if line.startswith("ROBOT ")) + 1 :]
        assert robots[0].split()[:2] == ["r1", "e-stopped"] and robots[1].split()[0] == "r2", table
        assert robots[1].split()[1] in ("standing", "moving"), table
        # released, it moves again, from where it stands
        await r1.send(b"rs000001:resume\r\n")
        (resumed,) = await r1.replies(1)
        assert isinstance(resumed, Done), resumed
        await r1.send(b"mv000003:move_joints:" + joints(Q0_DEG) + b"\r\nbr000001:break\r\n")
        moved, arrived = await r1.replies(2, timeout=20)
        assert isinstance(moved, Done) and isinstance(arrived, Done), (moved, arrived)
        back = await truth(bus, "r1")
        assert np.allclose(np.degrees(back.q), Q0_DEG, atol=0.05)
    r1.close()


async def test_estop_from_the_cli_and_a_client_names_robots_and_bad_names_are_refused(cell) -> None:
    config = cell.config
    done = await asyncio.to_thread(run_cell, "estop", "r2", "--config", str(cell.path))
    assert done.returncode == 0, done.stderr
    assert "r2: standing still" in done.stdout and "r1" not in done.stdout
    bad = await asyncio.to_thread(run_cell, "estop", "nobody", "--config", str(cell.path))
    assert bad.returncode == 2 and "nobody" in bad.stderr
    async with EventClient(config) as link:
        resumed = await link.resume(["r2"])
        assert set(resumed) == {2}
        took = await link.estop()  # every robot
        assert set(took) == {1, 2} and all(ms < 1000 for ms in took.values())
        await link.resume()
    r2 = await Conn.open(config.robots[1].skill_port)
    await r2.send(b"es000002:estop:r1,ghost\r\nes000003:estop:r1;x\r\n")
    unknown, malformed = await r2.replies(2)
    assert isinstance(unknown, Error) and unknown.code == "arguments" and "ghost" in unknown.text
    assert isinstance(malformed, Error) and malformed.code == "arguments"
    r2.close()


@pytest.mark.slow
async def test_a_task_script_estops_and_resumes_a_robot(cell) -> None:
    done = await asyncio.to_thread(run_cell, "run", str(EXAMPLE), "--config", str(cell.path))
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    assert "r1 e-stopped: standing still" in out
    assert "the interrupted move: stopped" in out and "a motion while stopped: stopped" in out
    assert "released; moved on to" in out


@pytest.mark.slow
async def test_a_stop_that_comes_late_behind_a_newer_release_is_not_obeyed(cell) -> None:
    """A hub that hung loses its bus connection; the forwarder drains the old connection's backlog
    after the new one's events, so an e-stop can reach the controller after its robot's release.
    The hub's own time says it is old: the controller ignores it (and counts it)."""
    config = cell.config
    r1 = await Conn.open(config.robots[0].skill_port)
    async with EventClient(config) as link, Bus.connect(config.bus, "test") as bus:
        old = time.monotonic_ns()
        await link.estop(["r1"])
        await counters_until(config, "controller", lambda c: c.get("stopped_on_link") == 1)
        await link.resume(["r1"])
        await counters_until(config, "controller", lambda c: c.get("stopped_on_link") == 0)
        RE = robot_pb2.RobotEvent
        late = RE(robot_id=1, name="r1", kind=RE.KIND_ESTOP, text="the backlog", t_ns=old)
        bus.publish("events/robot/r1", late)
        c = await counters_until(config, "controller", lambda c: c.get("stale_link_events", 0) >= 1)
        assert c["stopped_on_link"] == 0
        far = list(Q0_DEG)
        far[0] = 30.0
        await r1.send(b"mv000001:move_joints:" + joints(far) + b"\r\nbr000001:break\r\n")
        moved, arrived = await r1.replies(2, timeout=20)
        assert isinstance(moved, Done) and isinstance(arrived, Done), (moved, arrived)
    r1.close()


@pytest.mark.slow
async def test_a_data_plane_restarted_during_an_estop_holds_the_robot_stopped_until_resume(cell) -> None:
    """The data plane's process dies while r1 is e-stopped: the new one asks the hub what it holds
    (rlink.held) and sets r1's REG_stop again, r2 untouched; the resume then releases it as usual."""
    config = cell.config
    async with EventClient(config) as link, Bus.connect(config.bus, "test") as bus:
        dp = DataplaneClient(bus)
        await link.estop(["r1"])
        before = await dp.state([1, 2], robots_only=True)
        assert [r.stopped for r in before.robots] == [True, False]
        pid = next(s.last.pid for s in (await fetch_status(config)).services if s.name == "dataplane")
        os.kill(pid, signal.SIGKILL)
        deadline, after = time.monotonic() + 20, None
        while time.monotonic() < deadline:  # a new data plane (another boot id) with r1 held
            with contextlib.suppress(BusError, TimeoutError):
                st = await dp.state([1, 2], robots_only=True, timeout=0.5)
                if st.boot_id != before.boot_id and st.robots and st.robots[0].stopped:
                    after = st
                    break
            await asyncio.sleep(0.05)
        assert after is not None, "the restarted data plane did not hold r1 stopped"
        assert [r.stopped for r in after.robots] == [True, False]
        await link.resume(["r1"])
        released = await dp.state([1, 2], robots_only=True)
        assert [r.stopped for r in released.robots] == [False, False]
