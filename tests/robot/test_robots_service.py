"""The robots service in a real cell: UDP status and commands, and what it says on the bus."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from cell.bus import Bus, BusTimeout, RemoteError
from cell.config import parse_host_port
from cell.launcher import fetch_status
from cell.robot import datagram, udp
from cell.robot.datagram import Kind
from cell.v1 import robot_pb2
from tests.conftest import free_port

ROBOTS = [
    {"id": 1, "name": "r1", "skill_port": 0, "backend": "mujoco"},
    {"id": 2, "name": "r2", "skill_port": 0, "backend": "kinematic"},
]


class Plane:
    """Stands in for the data plane: receives status, answers with commands."""

    def __init__(self, listen: str) -> None:
        self.sock = udp.open_socket(*parse_host_port(listen))
        self.senders: dict[int, tuple] = {}
        self.last: dict[tuple[int, int], datagram.Datagram] = {}
        self.count = 0

    def pump(self, velocity: dict[tuple[int, int], float] | None) -> int:
        """Drain the status waiting; answer each with its joint's velocity (None: do not answer)."""
        n = 0
        while (got := udp.recv_batch(self.sock)) is not None:
            data, seg, sender, _ = got
            for i in range(0, len(data), seg):
                d = datagram.decode(data[i : i + seg], kind=Kind.STATUS)
                self.senders[d.robot_id] = sender
                self.last[(d.robot_id, d.joint_id)] = d
                n += 1
                if velocity is not None:
                    v = velocity.get((d.robot_id, d.joint_id), 0.0)
                    cmd = datagram.Datagram(d.robot_id, d.joint_id, Kind.COMMAND, d.seq, v, d.position)
                    self.sock.sendto(datagram.encode(cmd), sender)
        self.count += n
        return n

    async def run(self, seconds: float, velocity: dict | None) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.pump(velocity)
            await asyncio.sleep(0.0005)  # pacing of the polling loop; what matters is each pump

    def close(self) -> None:
        self.sock.close()


async def collect(sub, until, timeout: float = 10.0) -> list:
    got: list = []
    async with asyncio.timeout(timeout):
        while not until(got):
            got += await sub.recv_batch()
    return got


@pytest.mark.slow
async def test_robots_announce_stream_follow_commands_and_stop(start_cell) -> None:
    cell = await start_cell(run=["bus", "robots"], robots=[{**r, "skill_port": free_port()} for r in ROBOTS])
    plane = Plane(cell.config.dataplane.listen)
    try:
        async with Bus.connect(cell.config.bus, "tester") as bus:
            announce = await bus.subscribe("announce/robot/")
            truth = await bus.subscribe("truth/r1")
            events = await bus.subscribe("events/robot/")

            # plug and play: both robots announce themselves with their UDP address
            both = {"announce/robot/r1", "announce/robot/r2"}
            got = await collect(announce, lambda g: {e.topic for e in g} >= both)
            ann = {e.decode(robot_pb2.RobotAnnounce).name: e.decode(robot_pb2.RobotAnnounce) for e in got}
            assert (ann["r1"].robot_id, ann["r1"].backend, ann["r1"].joints) == (1, "mujoco", 6)
            assert ann["r2"].backend == "kinematic" and ann["r1"].udp_address != ann["r2"].udp_address
            assert list(ann["r1"].v_max) == pytest.approx([np.pi] * 6)

            # status arrives at 500 Hz per joint from the announced sockets
            plane.pump(None)  # what queued before now is not part of the measurement
            before, t0 = plane.count, time.monotonic()
            await plane.run(0.5, velocity=None)
            rate = (plane.count - before) / (time.monotonic() - t0) / 12
            assert 400 < rate < 600, rate
            assert {f"{h}:{p}" for h, p in [plane.senders[1]]} == {ann["r1"].udp_address}

            # commands move the robot: joint 0 of r1 at 0.3 rad/s, everything else held
            await plane.run(1.0, velocity={(1, 0): 0.3})
            assert plane.last[(1, 0)].velocity == pytest.approx(0.3, rel=0.01)
            assert abs(plane.last[(2, 0)].velocity) < 1e-6
            states = await collect(truth, lambda g: len(g) >= 5)
            last = states[-1].decode(robot_pb2.RobotTruth)
            assert last.qd[0] == pytest.approx(0.3, rel=0.02) and not last.stopped
            assert len(last.tool_pose) == 7

            # nobody answers any more: both robots make a protective stop, said on the bus
            stops = []

            async def watch() -> None:
                stops.extend(await collect(events, lambda g: len(g) >= 2, timeout=5))

            watcher = asyncio.create_task(watch())
            await plane.run(0.2, velocity=None)
            await watcher
            decoded = [e.decode(robot_pb2.RobotEvent) for e in stops]
            kinds = {(ev.name, ev.kind) for ev in decoded}
            stop = robot_pb2.RobotEvent.KIND_PROTECTIVE_STOP
            assert kinds == {("r1", stop), ("r2", stop)}
    finally:
        plane.close()


async def test_bad_datagrams_are_counted_and_the_robots_go_on(start_cell) -> None:
    cell = await start_cell(run=["bus", "robots"], robots=[{**r, "skill_port": free_port()} for r in ROBOTS])
    plane = Plane(cell.config.dataplane.listen)
    try:
        await plane.run(0.1, velocity=None)
        target = plane.senders[2]
        junk = [b"x" * 5, bytes(24), datagram.encode(datagram.Datagram(1, 0, Kind.COMMAND, 0, 1.0, 0.0))]
        for _ in range(10):
            for j in junk:  # too short; a status (kind 0) to a robot; r1's command sent to r2
                plane.sock.sendto(j, target)
        deadline = time.monotonic() + 10
        while True:
            status = await fetch_status(cell.config)
            robots = next(s for s in status.services if s.name == "robots")
            c = robots.last.counters
            if c["rejected.length"] >= 10 and c["rejected.kind"] >= 10 and c["rejected.robot"] >= 10:
                break
            assert time.monotonic() < deadline, dict(c)
            await asyncio.sleep(0.1)
        assert robots.health == "ok"
        before = plane.count
        await plane.run(0.2, velocity=None)
        assert plane.count - before > 0.2 * 500 * 12 * 0.8  # still streaming

        # fault injection is a bus method of each robot: bad requests are refused, saying why
        async with Bus.connect(cell.config.bus, "tester") as bus:
            for robot, seconds, why in ((("r2", 0.0, "seconds")), ("r2", 61.0, "seconds"), ("r1", 1.0, "r1")):
                with pytest.raises(RemoteError) as err:
                    await bus.request(
                        "robot/r2", "silence", robot_pb2.SilenceRequest(robot=robot, seconds=seconds)
                    )
                assert err.value.code == "bad_request" and why in err.value.message
            with pytest.raises(BusTimeout):  # nobody serves a robot the cell does not have
                await bus.request("robot/r9", "silence", robot_pb2.SilenceRequest(seconds=1.0), timeout=0.3)
            await bus.request("robot/r2", "silence", robot_pb2.SilenceRequest(robot="r2", seconds=0.5))
            plane.pump(None)  # (what r2 sent before: loopback delivered it before the reply left)
            plane.last.clear()
            await plane.run(0.2, velocity=None)
            assert {rid for rid, _ in plane.last} == {1}  # r2 is mute, r1 streams on
    finally:
        plane.close()
