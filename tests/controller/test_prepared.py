"""Motions prepared in the tables ahead of their moment (cell.controller.prepared), against a real
cell: armed starts fired by switch entries, TPStepper loops, alternates taken at the next TP."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cell.bus import Bus
from tests.controller.test_controller import (
    Q0,
    Truth,
    crossing_time,
    driving,
    fast_truth,
    max_accel,
    planned_crossing,
)


@pytest.mark.slow
@pytest.mark.parametrize("models", [False, True])
async def test_armed_robots_wait_and_leave_their_holds_together_when_fired(start_cell, models: bool) -> None:
    arms = fast_truth("kinematic", 2)
    if models:  # a UR5e and a UR10e: tick grids of their own (two emulator groups)
        arms[1]["model"] = "ur10e"
    async with driving(start_cell, arms) as (ctl, truth):
        delta = np.array([0.4, -0.3, 0.2, 0.0, 0.1, 0.3])
        armed = await ctl.arm({"r1": Q0 + delta, "r2": Q0 - delta})
        t_armed = ctl.link.now()
        await ctl.link.sleep_until(t_armed + 300_000_000)  # armed: loaded, and nobody moves
        for name in ("r1", "r2"):
            assert np.abs(truth.last(name) - Q0).max() < 1e-4
        result = await ctl.fire(armed)
        assert result.start_ns > t_armed + 300_000_000
        s1, s2 = (ctl.engine.last_fire[ctl.robot_id(n)] for n in ("r1", "r2"))
        if not models:
            assert s1 == s2
            t1, t2 = (crossing_time(truth.samples[n], Q0, 1e-3) for n in ("r1", "r2"))
            assert abs(t1 - t2) / 1e6 <= 2.0 + 0.5  # one status period (their grids are their own)
        else:  # r2 leaves at its first status after r1's: each follows its own plan as closely
            assert 0 <= s2 - s1 < 2_000_000 + 100_000
            t1, t2 = (
                crossing_time(truth.samples[n], Q0, 0.1) - planned_crossing(ctl.track(n).segment, 0.1)
                for n in ("r1", "r2")
            )
            # (within a status period, as above: a tick the host held up shifts one arm's truth by one;
            # 2.34 ms once in a fresh-clone run, well under 0.5 ms on a quiet machine)
            assert abs(t1 - t2) / 1e6 <= 2.0 + 0.5
        first = min(crossing_time(truth.samples[n], Q0, 1e-3) for n in ("r1", "r2"))
        assert abs(first - result.start_ns) / 1e6 < 60  # (1 mrad takes a while from rest)
        for name, goal in (("r1", Q0 + delta), ("r2", Q0 - delta)):  # and both settle where they were sent
            q, _ = await ctl.arrive(name, tolerance=1e-4, timeout=3.0)
            assert np.allclose(q, goal, atol=1e-4)


@pytest.mark.slow
async def test_a_loop_runs_its_laps_from_one_load_then_holds_where_it_began(start_cell) -> None:
    async with driving(start_cell, fast_truth("kinematic", 1)) as (ctl, truth):
        far = Q0 + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
        dp = ctl.dp
        loads_before = (await dp.state()).counters.get("tps_loaded", 0)
        run = await ctl.run_loop("r1", [far], speed=1.0, laps=3)
        assert await asyncio.wait_for(asyncio.shield(run.done), 20) == 3
        await ctl.wait_idle("r1")
        # three visits to the waypoint, each a lap apart, and back where it began
        q = np.array([s[1][0] for s in truth.samples["r1"] if s[0] >= run.start_ns])
        t = np.array([s[0] for s in truth.samples["r1"] if s[0] >= run.start_ns])
        peaks = t[1:-1][(q[1:-1] > 0.29) & (q[1:-1] >= q[:-2]) & (q[1:-1] > q[2:])]
        assert len(peaks) == 3, peaks
        assert np.allclose(np.diff(peaks), run.lap_ns, atol=10_000_000)
        assert np.allclose(truth.last("r1"), Q0, atol=1e-3)
        # one load for every lap: the TPs of one lap and its holds, however many laps
        loaded = (await dp.state()).counters.get("tps_loaded", 0) - loads_before
        assert 0 < loaded < 3 * (run.lap_ns / 1e9 * ctl.engine.rate_hz)
        # until ended: it is ended during its second lap, and runs two
        run = await ctl.run_loop("r1", [far], speed=1.0)
        await ctl.link.sleep_until(run.start_ns + run.lap_ns + run.lap_ns // 3)
        assert await ctl.end_loop("r1") == 2
        await ctl.wait_idle("r1")
        assert np.allclose(truth.last("r1"), Q0, atol=1e-3)


@pytest.mark.slow
async def test_a_prepared_alternate_is_taken_at_the_next_tp_without_planning(start_cell) -> None:
    async with driving(start_cell, fast_truth("kinematic", 1)) as (ctl, truth):
        main = await ctl.move_joints("r1", Q0 + np.array([1.2, -0.4, 0.3, 0, 0, 0]), speed=0.3, wait=False)
        retreat, detour = Q0 + np.array([-0.2, 0.1, 0, 0, 0, 0]), Q0 + np.array([0.5, 0.3, -0.3, 0, 0, 0])
        loaded = await ctl.prepare_alternates("r1", {"retreat": retreat, "detour": detour}, every=4)
        assert loaded > 0
        _, branches = ctl.engine.alternates[1]
        ks = [a.k for a in branches["detour"]]
        assert ks == list(range(ks[0], ks[0] + 4 * len(ks), 4)) and ks[-1] >= 40  # to the motion's end
        asked = ctl.link.now()
        assert asked < main.end_ns - 1_000_000_000  # (still under way)
        result = await ctl.take_alternate("r1", "detour")
        sw = ctl.engine.last_switch
        assert sw is not None and sw.lead_ms > 0  # the switch entry was in place before its TP
        # at the next branch point in reach: within a round trip, the margin and four sections
        assert (sw.t_branch_ns - asked) / 1e6 < 20 + 4 * 100 + 50
        near = [(t, q, qd) for t, q, qd in truth.samples["r1"] if abs(t - sw.t_branch_ns) < 300_000_000]
        t = np.array([s[0] for s in near]) / 1e9
        assert max_accel(t, np.array([s[2] for s in near])) <= 5.0 * 1.3  # no jump at the branch
        q_at = min(near, key=lambda s: abs(s[0] - sw.t_branch_ns))[1]
        assert np.abs(q_at - sw.q_pred).max() < 0.005  # the branch began where the robot was
        assert np.allclose(result.q_end, detour)
        q, _ = await ctl.arrive("r1", tolerance=1e-4, timeout=3.0)
        assert np.allclose(q, detour, atol=1e-4)


@pytest.mark.slow
async def test_task_scripts_loop_and_arm_alternates_through_the_controller_service(start_cell) -> None:
    from cell.bus import RemoteError
    from cell.master import Cell
    from cell.v1 import controller_pb2

    cell = await start_cell(run=["bus", "dataplane", "robots", "controller"], robots=fast_truth("kinematic"))
    async with Bus.connect(cell.config.bus, "script") as bus, asyncio.TaskGroup() as tg:
        truth = Truth()
        watcher = tg.create_task(truth.run(bus))
        script = Cell(cell.config, bus, {})
        M = controller_pb2.MoveRequest
        async with asyncio.timeout(10):  # the controller has heard from the robot
            while True:
                try:
                    await bus.request("controller", "pose", controller_pb2.RobotRequest(robot="r1"))
                    break
                except RemoteError:
                    await asyncio.sleep(0.05)
        q0_deg = np.degrees(Q0)
        assert await script.loop("r1", [(q0_deg + np.array([15, 0, 0, 0, 0, 0])).tolist()], laps=2) == 2
        arrive = controller_pb2.ArriveRequest(robot="r1", tolerance_rad=1e-4, timeout_s=3.0)
        here = await bus.request("controller", "arrive", arrive, controller_pb2.PoseReply, 5.0)
        assert np.allclose(here.joints, Q0, atol=1e-4)  # back where the laps began
        # a motion under way, alternates prepared for it, one armed by an event on the bus
        goal = Q0 + np.array([1.2, -0.4, 0.3, 0, 0, 0])
        await bus.request(
            "controller", "move", M(robot="r1", values=goal.tolist(), speed=40, start_only=True)
        )
        retreat = q0_deg + np.array([-10, 5, 0, 0, 0, 0])
        assert await script.prepare_alternates("r1", {"retreat": retreat.tolist()}, every=4) > 0
        script.arm_alternate("r1", "retreat")
        async with asyncio.timeout(10):
            while np.abs(truth.last("r1") - np.radians(retreat)).max() > 1e-3:
                await asyncio.sleep(0.05)
        # bad requests get clear errors and the service stays up
        with pytest.raises(RemoteError, match="plan"):
            await script.take_alternate("r1", "nowhere")
        with pytest.raises(RemoteError, match="bad_request"):
            await script.loop("r1", [[1.0, 2.0]], laps=1)
        with pytest.raises(RemoteError, match="unknown_robot"):
            await script.prepare_alternates("nobody", {"a": q0_deg.tolist()})
        assert await script.loop("r1", [q0_deg.tolist(), retreat.tolist()], laps=1) == 1
        watcher.cancel()
