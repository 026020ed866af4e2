"""The dataplane service in a real cell: robots follow trajectories loaded over the bus."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from cell.bus import Bus, RemoteError
from cell.config import parse_host_port
from cell.dataplane.client import DataplaneClient
from cell.dataplane.tables import TP
from cell.launcher import fetch_status
from cell.robot import datagram, udp
from cell.robot.datagram import Datagram, Kind
from cell.v1 import dataplane_pb2, robot_pb2
from tests.conftest import free_port

Q0 = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]


def robots(backend: str) -> list[dict]:
    return [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": backend}]


async def last_truth(bus: Bus, name: str) -> robot_pb2.RobotTruth:
    sub = await bus.subscribe(f"truth/{name}")
    try:
        env = await sub.recv(timeout=5)
        return env.decode(robot_pb2.RobotTruth)
    finally:
        sub.close()


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["kinematic", "mujoco"])
async def test_robot_follows_a_loaded_trajectory_to_its_end(start_cell, backend: str) -> None:
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=robots(backend))
    async with Bus.connect(cell.config.bus, "controller") as bus:
        dp = DataplaneClient(bus)
        goal = [Q0[0] + 0.3, Q0[1] - 0.2, *Q0[2:]]
        steps = 20  # 0.1 s sections along a straight joint-space line, then hold at the goal
        line = np.linspace(Q0, goal, steps + 1)
        vel = (np.array(goal) - np.array(Q0)) / (steps * 0.1)
        tps = [TP(1, 0, 0, 0.1, Q0, [0.0] * 6)]  # hold where it is (self-loop)
        tps += [TP(1, k, k + 1, 0.1, line[k].tolist(), vel.tolist()) for k in range(1, steps)]
        tps += [TP(1, steps, steps, 0.1, goal, [0.0] * 6)]  # the last TP holds
        reply = await dp.update(insert=tps)
        assert (reply.inserted, reply.loaded) == (steps + 1, steps + 1)
        start = reply.now_ns + 200_000_000
        await dp.update(registers=[(1, 0, start)], switches=[(1, 0, 1)])  # leave the hold at `start`
        deadline = time.monotonic() + 10
        while True:
            st = await dp.state()
            if next(r.tp_id for r in st.robots if r.robot_id == 1) == steps:
                break
            assert time.monotonic() < deadline, st
            await asyncio.sleep(0.05)
        await asyncio.sleep(1.0)  # let it settle on the last TP (the P term closes the gap)
        truth = await last_truth(bus, "r1")
        assert np.allclose(truth.q, goal, atol=2e-3), (list(truth.q), goal)
        assert abs(truth.qd[0]) < 1e-2
        counters = (await dp.state()).counters
        assert counters["steps"] >= steps and counters["commands_out"] > 1000
        assert counters["packets_in"] >= counters["commands_out"]


async def test_refusals_and_bad_datagrams(start_cell) -> None:
    # (the user-space data plane: its constants can be reloaded, and junk reaches it from loopback;
    # the XDP program's maps are sized for one n_bits, and its refusals are tests/dataplane/test_xdp.py's)
    dp_section = {"listen": f"127.0.0.1:{free_port()}", "backend": "native"}
    cell = await start_cell(
        run=["bus", "dataplane"], robots=robots("kinematic"), sections={"dataplane": dp_section}
    )
    async with Bus.connect(cell.config.bus, "controller") as bus:
        dp = DataplaneClient(bus)
        with pytest.raises(RemoteError) as info:
            await dp.update(insert=[TP(99, 1, 1, 0.1, [0.0] * 6, [0.0] * 6)])
        assert info.value.code == "unknown_robot"
        with pytest.raises(RemoteError) as info:
            await dp.update(registers=[(1, 42, 0)])
        assert info.value.code == "unknown_tp"
        assert (await dp.state()).loaded == 0  # nothing of a refused batch was applied
        columns = {"robot_id": [1], "id": [1], "next_id": [1], "duration_s": [0.1], "joints": [6]}
        tps = dataplane_pb2.TrajectoryPoints(**columns, positions=[0.0] * 5, velocities=[0.0] * 6)
        bad = dataplane_pb2.TableUpdate(insert=tps)  # columns that disagree: 6 joints said, 5 values given
        with pytest.raises(RemoteError) as info:
            await bus.request("dataplane", "update", bad, dataplane_pb2.UpdateReply, 5)
        assert info.value.code == "bad_request" and "6 joint values expected" in str(info.value)
        assert (await dp.state()).loaded == 0
        # a robot is the controller's that flushed it last (taking it over): one that had loaded it
        # before is refused whole, saying so; one new to it, or a tool (no controller id), is not
        first, second = DataplaneClient(bus, controller=11), DataplaneClient(bus, controller=22)
        tp = TP(1, 5, 5, 0.1, [0.0] * 6, [0.0] * 6)
        await first.update(flush=[1])
        await second.update(flush=[1])
        with pytest.raises(RemoteError) as info:
            await first.update(insert=[tp])
        assert info.value.code == "taken" and "another controller" in info.value.message
        assert (await dp.state()).loaded == 0
        assert [r.controller for r in (await dp.state([1])).robots] == [22]
        assert (await second.update(insert=[tp])).inserted == 1
        assert (await DataplaneClient(bus, controller=33).update(remove=[(1, 5)])).removed == 1
        # new controller constants: tables regenerated and swapped in; bad ones refused
        reply = await dp.load_constants([1.0] * 6, [4.0] * 6, 6, [1.0] * 6)
        assert reply.transform_entries == 3 * 6 * 2 * (2**6 + 57 * 2**5)
        assert 0 < reply.limit_entries <= 6 * 2 * 63
        for bad in ([1.0] * 6, [4.0] * 6, 8, [20.0] * 6), ([1.0] * 5, [4.0] * 5, 8, [1.0] * 5):
            with pytest.raises(RemoteError) as info:
                await dp.load_constants(*bad)
            assert info.value.code == "bad_request"
        # a peer sending junk: counted and dropped, and status is still answered
        plane = parse_host_port(cell.config.dataplane.listen)
        sock = udp.open_socket("127.0.0.1")
        try:
            for junk in (b"abc", bytes(23), datagram.encode(Datagram(1, 0, Kind.COMMAND, 0, 0.0, 0.0))):
                sock.sendto(junk, plane)
            sock.sendto(datagram.encode(Datagram(1, 9, Kind.STATUS, 0, 0.0, 0.0)), plane)
            sock.sendto(datagram.encode(Datagram(1, 2, Kind.STATUS, 77, 0.5, 0.25)), plane)
            async with asyncio.timeout(5):
                while (got := udp.recv_batch(sock)) is None:
                    await asyncio.sleep(0.005)
            answer = datagram.decode(got[0], kind=Kind.COMMAND)
            assert (answer.robot_id, answer.joint_id, answer.seq, answer.velocity) == (1, 2, 77, 0.0)  # hold
            assert answer.position == pytest.approx(0.25)
        finally:
            sock.close()
        deadline = time.monotonic() + 5
        while True:
            c = next(
                s for s in (await fetch_status(cell.config)).services if s.name == "dataplane"
            ).last.counters
            if c["rejected.length"] >= 2 and c["rejected.kind"] >= 1 and c["rejected.joint"] >= 1:
                break
            assert time.monotonic() < deadline, dict(c)
            await asyncio.sleep(0.1)
        # a controller taking over flushes what it did not load: every TP of the robot, its registers
        await dp.update(insert=[TP(1, 7, 8, 0.1, Q0, [0.0] * 6), TP(1, 8, 8, 0.1, Q0, [0.0] * 6)])
        reply = await dp.update(registers=[(1, 7, 0)])
        boot = reply.boot_id
        assert boot != 0 and (await dp.state()).boot_id == boot  # one per data-plane start
        reply = await dp.update(flush=[1])
        assert reply.removed == 2 and reply.loaded == 0 and reply.boot_id == boot
        st = await dp.state()
        assert next(r.tp_id for r in st.robots if r.robot_id == 1) == -1
        with pytest.raises(RemoteError) as info:
            await dp.update(flush=[99])
        assert info.value.code == "unknown_robot"


def test_a_robot_is_pinned_to_its_first_sender_until_it_goes_quiet() -> None:
    from cell.config import load_config
    from cell.dataplane.pipeline import QUIET_NS
    from cell.dataplane.plane import DataPlane

    rob = [{"id": 1, "name": "r1", "skill_port": free_port()}]
    dp = {"listen": f"127.0.0.1:{free_port()}"}
    plane = DataPlane(load_config(overrides={"robots": rob, "dataplane": dp}))
    addr = plane.sock.getsockname()
    robot, intruder = udp.open_socket("127.0.0.1"), udp.open_socket("127.0.0.1")
    try:

        def send(sock, pos: float) -> int:
            recs = datagram.empty(6)
            datagram.pack(recs, 1, np.arange(6), Kind.STATUS, 1, 0.0, pos)
            udp.Sender(sock, datagram.SIZE).send(memoryview(recs.view(np.uint8)), addr)
            return plane.handle()

        def answered(sock) -> bool:
            return udp.recv_batch(sock) is not None

        assert send(robot, 0.1) == 6 and answered(robot)
        registers = plane.tables.status_pos[1].copy()
        assert send(intruder, 0.9) == 0 and not answered(intruder)  # dropped, counted, not answered
        assert plane.rejected["spoofed"] == 6
        assert (plane.tables.status_pos[1] == registers).all()  # its registers untouched
        assert plane.robot_addr[1] == robot.getsockname()  # stop commands still go to the robot
        assert send(robot, 0.2) == 6 and answered(robot)
        plane.tables.status_ns[1] -= QUIET_NS + 1  # the robot fell silent (a restart on a new port)
        assert send(intruder, 0.3) == 6 and answered(intruder)  # re-pinned to the new address
        assert send(robot, 0.4) == 0 and plane.rejected["spoofed"] == 12
        assert plane.robot_addr[1] == intruder.getsockname()
    finally:
        for s in (robot, intruder, plane.sock):
            s.close()
