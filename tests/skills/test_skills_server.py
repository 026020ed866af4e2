"""The skill servers in a live cell, over raw TCP bytes."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from cell.bus import Bus
from cell.launcher import fetch_status
from cell.robot.arm import arm_model
from cell.robot.pose import to_adept
from cell.skills.protocol import Done, Error, ReplyReader
from cell.v1 import skills_pb2
from tests.conftest import free_port

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
SKILLS = ["bus", "dataplane", "robots", "controller", "skills"]


class Conn:
    """A raw client connection: bytes out, parsed replies in."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer, self.parser, self.got = reader, writer, ReplyReader(), []

    @classmethod
    async def open(cls, port: int) -> Conn:
        async with asyncio.timeout(10):
            while True:
                try:
                    return cls(*await asyncio.open_connection("127.0.0.1", port))
                except ConnectionRefusedError:
                    await asyncio.sleep(0.05)

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def replies(self, n: int, timeout: float = 20.0):
        async with asyncio.timeout(timeout):
            while len(self.got) < n:
                data = await self.reader.read(4096)
                assert data, "the server closed the connection"
                self.got += self.parser.feed(data)
        out, self.got = self.got[:n], self.got[n:]
        return out

    def close(self) -> None:
        self.writer.close()


@pytest.fixture
async def cell(start_cell):
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic"}]
    return await start_cell(run=SKILLS, robots=robots)


def pose_deg(q: np.ndarray) -> np.ndarray:
    return np.array(to_adept(*arm_model().fk(q)))


@pytest.mark.slow
async def test_motions_are_answered_when_started_and_break_when_arrived(cell) -> None:
    c = await Conn.open(cell.config.robots[0].skill_port)
    goal = Q0 + np.array([0.3, -0.2, 0.2, 0.1, 0.0, 0.4])
    deg = ",".join(f"{math.degrees(v):.3f}" for v in goal)
    # three messages in one segment: set_speed, a motion, break
    await c.send(f"00000001:set_speed:50\r\n00000002:move_joints:{deg}\r\n00000003:break\r\n".encode())
    speed, move, brk = await c.replies(3)
    assert all(isinstance(r, Done) for r in (speed, move, brk)), (speed, move, brk)
    assert [r.id for r in (speed, move, brk)] == ["00000001", "00000002", "00000003"]
    assert np.allclose(move.pose, pose_deg(goal), atol=0.01)  # the motion's end (joints sent to 0.001 deg)
    assert np.allclose(brk.pose, pose_deg(goal), atol=0.5)  # measured: there within tolerance
    # the motion was answered when it started, break when the robot had arrived (a 50% motion: >1 s);
    # relative, not an absolute bound: a loaded machine plans slower, and the robot moves no faster
    assert brk.t_end - move.t_start > 1.0
    assert move.t_end - move.t_start < 0.5 * (brk.t_end - move.t_start)
    assert speed.t_start <= speed.t_end <= move.t_start <= move.t_end <= brk.t_start <= brk.t_end
    # a relative move in the tool frame: 20 mm along the tool's z, then break
    await c.send(b"00000004:move_rel_tool:0,0,20,0,0,0\r\n00000005:break\r\n")
    rel, brk2 = await c.replies(2)
    assert isinstance(rel, Done) and isinstance(brk2, Done)
    assert abs(np.linalg.norm(np.array(brk2.pose[:3]) - np.array(brk.pose[:3])) - 20.0) < 0.5
    c.close()


async def test_errors_are_answered_and_the_connection_stays_usable(cell) -> None:
    bus_cfg = cell.config.bus
    async with Bus.connect(bus_cfg, "watcher") as bus:
        air = await bus.subscribe("skills/r1/air")
        traces = await bus.subscribe("skills/r1/trace")
        c = await Conn.open(cell.config.robots[0].skill_port)
        part = (
            b"0000000a:move_to:3000,0,0,0,180,0\r\n0000000b:fly\r\nnonsense\r\n0000000c:move_joints:1,2\r\n"
        )
        await c.send(part[:20])
        await c.send(part[20:])  # one message split over two segments
        await c.send(b"0000000d:enable_air\r\n" + b"0000000e:move_to:" + b"9" * 2000 + b"\r\n")
        got = await c.replies(6)
        codes = {r.id + ":" + (r.code if isinstance(r, Error) else "done") for r in got}
        assert codes == {
            "0000000a:unreachable",
            "0000000b:unknown_skill",
            "00000000:malformed",
            "0000000c:arguments",
            "0000000d:done",
            "0000000e:line_too_long",
        }, got
        state = (await air.recv(timeout=5)).decode(skills_pb2.AirState)
        assert state.on and state.robot == "r1"
        # and the connection still works, as does a second client, served in arrival order
        c2 = await Conn.open(cell.config.robots[0].skill_port)
        await c.send(b"0000000f:disable_air\r\n")
        await c2.send(b"00000010:break\r\n")
        (a,), (b,) = await c.replies(1), await c2.replies(1)
        assert isinstance(a, Done) and isinstance(b, Done)
        # one robot's commands run one at a time in arrival order: the two never overlap (which
        # came first is the network's business: two connections are not ordered)
        assert a.t_end <= b.t_start + 1e-3 or b.t_end <= a.t_start + 1e-3, (a, b)
        seen = set()
        async with asyncio.timeout(5):
            while not {"0000000f", "00000010"} <= seen:
                t = (await traces.recv(timeout=5)).decode(skills_pb2.SkillTrace)
                assert t.received_ns <= t.started_ns <= t.answered_ns
                seen.add(t.id)
        c.close()
        c2.close()


@pytest.mark.slow
async def test_a_non_motion_ack_reports_the_pose_the_server_holds_without_asking_anyone(cell) -> None:
    """set_speed and the air skills answer with the tool pose of the robot's latest state broadcast
    (truth/<robot>, at most one period old): the same pose `break` measures, without two bus hops."""
    c = await Conn.open(cell.config.robots[0].skill_port)
    goal = Q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.1, 0.0])
    deg = ",".join(f"{math.degrees(v):.3f}" for v in goal)
    await c.send(f"00000011:move_joints:{deg}\r\n00000012:break\r\n".encode())
    _, brk = await c.replies(2)
    await c.send(b"00000013:set_speed:30\r\n00000014:enable_air\r\n00000015:disable_air\r\n")
    acks = await c.replies(3)
    for ack in acks:
        assert isinstance(ack, Done)
        assert np.allclose(ack.pose[:3], brk.pose[:3], atol=0.2)  # mm: the same place, by another path
        assert np.allclose(ack.pose[3:], brk.pose[3:], atol=0.1)  # deg
    held = asked = 0.0
    async with asyncio.timeout(10):  # the server reports its counters once a second
        while held + asked < 3:
            status = await fetch_status(cell.config)
            counters = next(s for s in status.services if s.name == "skills").last.counters
            held, asked = counters["r1.held_pose_acks"], counters["r1.asked_pose_acks"]
    # each ack's pose came one way or the other; the held one unless the machine held up every
    # broadcast for two deliveries (then the controller was asked: counted, never a wrong pose)
    assert held + asked == 3 and held >= 1, (held, asked)
    c.close()


async def test_what_one_peer_can_take_is_capped_and_counted(start_cell) -> None:
    robots = [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic"}]
    caps = {"max_connections": 3, "max_connections_per_peer": 2, "max_pending": 4, "line_timeout_s": 0.5}
    cell = await start_cell(run=SKILLS, robots=robots, sections={"skills": caps})
    port = robots[0]["skill_port"]
    a, b = await Conn.open(port), await Conn.open(port)
    await a.send(b"sp000001:set_speed:50\r\n")
    assert isinstance((await a.replies(1))[0], Done)  # (both are in)
    c = await Conn.open(port)  # a third from the same address: refused, told why, closed
    (busy,) = await c.replies(1)
    assert isinstance(busy, Error) and busy.code == "busy" and "127.0.0.1" in busy.text
    assert await c.reader.read(100) == b""
    # a message begun and not ended in line_timeout_s: told busy, closed; the other connection lives on
    await b.send(b"sp000002:set_sp")
    (slow,) = await b.replies(1, timeout=5)
    assert isinstance(slow, Error) and slow.code == "busy" and "must end within" in slow.text
    # a flood of commands: the server reads max_pending ahead, answers every one, in order
    await a.send(b"".join(b"sp%06d:set_speed:50\r\n" % i for i in range(200)))
    flood = await a.replies(200, timeout=30)
    assert [r.id for r in flood] == [f"sp{i:06d}" for i in range(200)]
    assert all(isinstance(r, Done) for r in flood)
    # a 1 MB line is refused as too long, and the connection still serves
    await a.send(b"x" * 1_000_000 + b"\r\nsp999999:set_speed:20\r\n")
    long, ok = await a.replies(2)
    assert isinstance(long, Error) and long.code == "line_too_long" and isinstance(ok, Done)
    wanted = ("r1.refused_connections", "r1.slow_lines", "r1.paused_reads")
    async with asyncio.timeout(10):  # (counters reach `cell status` with the next heartbeats)
        while True:
            c = next(
                s for s in (await fetch_status(cell.config)).services if s.name == "skills"
            ).last.counters
            if all(c[k] >= 1 for k in wanted):
                break
            await asyncio.sleep(0.1)
    a.close()
