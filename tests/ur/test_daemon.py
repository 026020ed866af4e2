"""The daemon end to end: a robot of backend "ur" is a UR controller reached only over its UR interfaces
(here the cell's own emulated arm offering nothing else, as URSim or a real UR5e), and the cell drives
it through the data plane exactly as it drives its own arms: the real bytes both ways."""

from __future__ import annotations

import asyncio
import os

import dashboard_client
import numpy as np
import pytest
import rtde_receive

from cell.bus import Bus, RemoteError
from cell.controller.controller import Controller
from cell.launcher import fetch_status
from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics
from cell.robot.node import UR_SCRIPT
from cell.v1 import controller_pb2, robot_pb2
from tests.conftest import free_port, run_cell
from tests.ur.test_ur_control import CELL, Q0, Events, _counter

M = controller_pb2.MoveRequest
RE = robot_pb2.RobotEvent


def ur_robot() -> list[dict]:
    return [
        {
            "id": 1,
            "name": "r1",
            "skill_port": free_port(),
            "backend": "ur",
            "ur_emulate": "mujoco",
            "truth_hz": 500,
        }
    ]


UR = {"ur": {"daemon_restart_s": 0.3}}


async def _ignored_once_running(config) -> float:
    """commands_ignored in the first status (one snapshot) that shows r1's daemon program running."""
    async with asyncio.timeout(10):
        while True:
            status = await fetch_status(config)
            c = next(s for s in status.services if s.name == "robots").last.counters
            if c.get("robot.r1.state", UR_SCRIPT) != UR_SCRIPT:
                return c["commands_ignored"]
            await asyncio.sleep(0.05)


@pytest.mark.slow
async def test_the_demo_motions_run_through_the_daemon_on_an_arm_reached_only_over_rtde(start_cell) -> None:
    # (the controller is this test's own: no controller service beside it)
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=ur_robot(), sections=UR)
    host = cell.config.robots[0].ur_host
    recv = await asyncio.to_thread(rtde_receive.RTDEReceiveInterface, host, 500.0, ["timestamp", "actual_q"])
    kin = Kinematics()
    # the data plane's answers to the statuses the daemon sent before its program ran were not the
    # arm's to take (counted and ignored, by design): from the status saying it runs, none may be
    ignored_before = await _ignored_once_running(cell.config)
    async with Bus.connect(cell.config.bus, "test") as bus, Controller(bus, cell.config) as ctl:
        ann = await bus.request("robot/r1", "announce", robot_pb2.AnnounceRequest(), robot_pb2.RobotAnnounce)
        assert ann.backend == "ur" and ann.status_hz == 500 and ann.window_origin_ns > 0
        truth: dict[int, np.ndarray] = {}
        sub = await bus.subscribe("truth/r1")

        async def follow() -> None:
            async for env in sub:
                m = env.decode(robot_pb2.RobotTruth)
                truth[m.tick] = np.array(m.q)  # (the daemon's tick: the controller's own cycle number)

        seen: dict[int, np.ndarray] = {}

        async def poll() -> None:
            while True:
                t1, q, t2 = recv.getTimestamp(), recv.getActualQ(), recv.getTimestamp()
                if t1 == t2:
                    seen.setdefault(round(t1 / 0.002), np.array(q))
                await asyncio.sleep(0.0005)

        async with asyncio.TaskGroup() as tg:
            watchers = [tg.create_task(follow()), tg.create_task(poll())]
            # the demo's motions: joint moves, and a straight line of the tool
            goal = Q0 + np.array([0.5, -0.3, 0.2, 0.1, 0.0, 0.4])
            await ctl.move_joints("r1", goal, speed=0.6)
            await ctl.arrive("r1", tolerance=1e-3, timeout=3.0)
            assert np.abs(np.array(recv.getActualQ()) - goal).max() <= 1e-3  # as the controller says
            pos, rot = kin.fk(goal)
            await ctl.move_linear("r1", pos + np.array([0.0, 0.1, -0.05]), rot, speed=1.0)
            await ctl.arrive("r1", tolerance=1e-3, timeout=3.0)
            q_end = np.array(recv.getActualQ())
            assert np.linalg.norm(kin.fk(q_end)[0] - (pos + np.array([0.0, 0.1, -0.05]))) < 1e-3
            await ctl.move_joints("r1", Q0, speed=0.6)
            for w in watchers:
                w.cancel()
    recv.disconnect()
    # the cell's truth of the arm is what its controller's RTDE says, cycle for cycle
    both = sorted(set(seen) & set(truth))
    assert len(both) > 100
    for t in both:
        assert np.array_equal(seen[t], truth[t]), t
    c = {k: await _counter(cell.config, k) for k in ("daemon.windows_written", "daemon.out_of_order",
                                                     "daemon.programs_sent", "commands_ignored")}  # fmt: skip
    assert c["daemon.windows_written"] > 100 and c["daemon.out_of_order"] == 0
    assert c["daemon.programs_sent"] == 1 and c["commands_ignored"] == ignored_before
    status = await asyncio.to_thread(run_cell, "status", "--config", str(cell.path))
    assert (
        "r1         127.0.1.1        ur5e (emulated, mujoco; the daemon's program: running)" in status.stdout
    )
    # the daemon's group ticks in Python: the robots' Python at FIFO 50 where SCHED_FIFO is granted,
    # under a budget (cell.rtbudget) that keeps it from the kernel's RT throttling
    robots = next(s for s in (await fetch_status(cell.config)).services if s.name == "robots").last
    if os.geteuid() == 0:
        assert "rest fifo 50" in robots.sched and "process.rt.budget_spent" in robots.counters, robots


async def _move_once_heard(bus: Bus, goal: np.ndarray) -> None:
    """r1 moved to goal once the controller too has heard the daemon's program runs again: the test
    and the controller each hear the daemon's event on a subscription of their own, the controller
    maybe a moment later (a move refused meanwhile says the arm's last state; asked again, at most
    for 5 s)."""
    async with asyncio.timeout(5):
        while True:
            try:
                await bus.request("controller", "move", M(robot="r1", values=goal.tolist()), timeout=20)
                return
            except RemoteError as exc:
                if "does not let the arm move" not in str(exc) and "another program" not in str(exc):
                    raise
            await asyncio.sleep(0.05)


@pytest.mark.slow
async def test_the_daemon_gives_way_to_the_controllers_state_and_takes_the_arm_back(start_cell) -> None:
    cell = await start_cell(run=CELL, robots=ur_robot(), sections=UR)
    host, ur = cell.config.robots[0].ur_host, cell.config.ur
    dash = dashboard_client.DashboardClient(host)
    await asyncio.to_thread(dash.connect)
    try:
        async with Bus.connect(cell.config.bus, "test") as bus:
            events = Events(await bus.subscribe("events/robot/r1"))
            far = M(robot="r1", values=(Q0 + np.array([1.5, 0, 0, 0, 0, 0])).tolist(), speed=5)
            move = asyncio.create_task(bus.request("controller", "move", far, timeout=30))
            # powered off under the motion: the motion ends saying why, and nothing else starts
            await asyncio.sleep(0.3)
            dash.powerOff()
            why = await events.wait(RE.KIND_PROGRAM, "does not let the arm move: POWER_OFF")
            assert why == "the UR controller at 127.0.1.1 does not let the arm move: POWER_OFF, NORMAL"
            try:
                await move
            except RemoteError as exc:
                assert "POWER_OFF" in str(exc)
            else:
                raise AssertionError("the motion was answered done on an arm that was powered off")
            try:
                await bus.request("controller", "move", M(robot="r1", values=Q0.tolist()), timeout=10)
            except RemoteError as exc:
                assert "POWER_OFF" in str(exc)
            else:
                raise AssertionError("a motion was taken for an arm that is powered off")
            # powered on and released as a UR is: the daemon sends its program again, and drives
            dash.powerOn()
            dash.brakeRelease()
            await events.wait(
                RE.KIND_PROGRAM_END, "the daemon's program runs on the UR controller at 127.0.1.1"
            )
            await _move_once_heard(bus, Q0)
            # another program on the primary interface holds the arm while it runs
            _, writer = await asyncio.open_connection(host, ur.primary_port)
            writer.write(b"def other():\n  sleep(0.5)\nend\n")
            await writer.drain()
            await events.wait(RE.KIND_PROGRAM, "another program runs on the UR controller")
            await events.wait(RE.KIND_PROGRAM_END, "the daemon's program runs")  # (sent again once it ended)
            writer.close()
            await _move_once_heard(bus, Q0 + 0.1)
            assert await _counter(cell.config, "daemon.programs_sent") == 3
    finally:
        dash.disconnect()


@pytest.mark.slow
async def test_the_controller_going_away_stops_the_arm_by_its_program_and_the_daemon_picks_it_up_again(
    start_cell,
) -> None:
    cell = await start_cell(run=CELL, robots=ur_robot(), sections=UR)
    host = cell.config.robots[0].ur_host
    recv = await asyncio.to_thread(rtde_receive.RTDEReceiveInterface, host, 500.0, ["timestamp", "actual_qd"])
    try:
        async with Bus.connect(cell.config.bus, "test") as bus:
            events = Events(await bus.subscribe("events/robot/r1"))
            far = M(robot="r1", values=(Q0 + np.array([2.0, 0, 0, 0, 0, 0])).tolist(), speed=50)
            move = asyncio.create_task(bus.request("controller", "move", far, timeout=30))
            async with asyncio.timeout(10):
                while recv.getActualQd()[0] < 0.3:  # under way
                    await asyncio.sleep(0.005)
            cut = robot_pb2.SilenceRequest(robot="r1", seconds=1.5)
            await bus.request("robot/r1", "silence", cut, robot_pb2.SilenceReply)
            t_cut, qd_cut = recv.getTimestamp(), recv.getActualQd()[0]
            why = await events.wait(RE.KIND_PROGRAM, "is unreachable")
            assert "the link to the controller was cut for 1.5 s" in why
            try:
                await move
            except RemoteError as exc:
                assert "unreachable" in str(exc) or "silent" in str(exc) or "stopped" in str(exc), exc
            else:
                raise AssertionError("a motion was answered done while its arm's controller was gone")
            # the program on the controller sees no new window and stops the arm on its own
            async with asyncio.timeout(5):
                while abs(recv.getActualQd()[0]) > 1e-3:
                    await asyncio.sleep(0.005)
            # within its watchdog's cycles ((3 + 1) windows of 4: 32 ms) and the ramp down at the arm's
            # deceleration (it may still speed up over those cycles), long before the link is back
            a_max = arm_model("ur5e").limits.a_max[0]
            assert recv.getTimestamp() - t_cut <= 0.032 + (qd_cut + 0.032 * a_max) / a_max + 0.05
            # the link back: the daemon finds its program still running and takes it up (not re-sent)
            await events.wait(RE.KIND_PROGRAM_END, "the daemon's program runs", timeout=10)
            await bus.request("controller", "move", M(robot="r1", values=Q0.tolist()), timeout=20)
            assert await _counter(cell.config, "daemon.programs_sent") == 1
            assert await _counter(cell.config, "daemon.lost") == 1
    finally:
        recv.disconnect()
