"""UR's external_control program on a running cell's arm, over real sockets: the test stands where
UR's client library stands (its reverse, trajectory and script command servers, the program sent
headless to the primary interface) and the arm connects back, from its own address."""

from __future__ import annotations

import asyncio
import struct

import numpy as np
import pytest
import rtde_receive

from cell.bus import Bus
from cell.ur import primary
from cell.ur.external import (
    COMMAND,
    POINT,
    RESULT,
    REVERSE,
    Command,
    Mode,
    MotionType,
    Result,
    TrajectoryAction,
    client_program,
)
from cell.v1 import robot_pb2
from tests.conftest import free_port

NAMES = ("trajectory_socket", "script_command_socket", "reverse_socket")
Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
M = 1_000_000


class Client:
    """UR's client library's side: three servers the program connects back to, and the primary
    interface the program is sent over (whose messages it reads)."""

    def __init__(self) -> None:
        self.conns: dict[str, tuple[asyncio.StreamReader, asyncio.StreamWriter]] = {}
        self.servers: list[asyncio.Server] = []
        self.ports: dict[str, int] = {}
        self.connected = asyncio.Event()
        self.buf = bytearray()  # from the primary interface: not yet a whole package
        self.heard: list[tuple[int, bytes]] = []  # its packages not yet looked at

    async def start(self, arm_host: str, primary_port: int, after: str = "") -> None:
        """`after`: lines appended after the program's control loop (as UR's client library's
        ExternalControlProgramTest appends them)."""
        for name in NAMES:

            def accept(r: asyncio.StreamReader, w: asyncio.StreamWriter, name: str = name) -> None:
                self.conns[name] = (r, w)
                if len(self.conns) == len(NAMES):
                    self.connected.set()

            server = await asyncio.start_server(accept, "127.0.0.1", 0)
            self.servers.append(server)
            self.ports[name] = server.sockets[0].getsockname()[1]
        self.primary = await asyncio.open_connection(arm_host, primary_port)
        script = client_program("127.0.0.1", self.ports)
        script = (
            script.removesuffix("end\n") + "".join(f"\t{line}\n" for line in after.splitlines()) + "end\n"
        )
        self.primary[1].write(script.encode())
        async with asyncio.timeout(5):
            await self.connected.wait()

    async def said(self, kind: primary.RobotMessage, words: bytes) -> bytes:
        """The next message of that kind with those words, from the primary interface."""
        while True:
            while self.heard:
                k, body = self.heard.pop(0)
                if k == primary.ROBOT_MESSAGE:
                    got = primary.read_robot_message(body)
                    if got[0] == kind and words in got[1]:
                        return got[1]
            self.buf += await self.primary[0].read(65536)
            self.heard += primary.split(self.buf)

    def send(self, name: str, data: bytes) -> None:
        self.conns[name][1].write(data)

    def close(self) -> None:
        for _, w in self.conns.values():
            w.close()
        self.primary[1].close()
        for s in self.servers:
            s.close()


def robots() -> list[dict]:
    return [{"id": 1, "name": "r1", "skill_port": free_port(), "backend": "kinematic", "truth_hz": 500}]


@pytest.mark.slow
async def test_the_program_connects_back_runs_a_spline_trajectory_and_stops_when_told(start_cell) -> None:
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=robots())
    host = cell.config.robots[0].ur_host
    client = Client()
    # what the program does once control stops: it opens a socket to the client's host and writes
    heard: asyncio.Queue[tuple[str, bytes]] = asyncio.Queue()

    async def hear(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await heard.put((w.get_extra_info("peername")[0], await r.read()))
        w.close()

    told = await asyncio.start_server(hear, "127.0.0.1", 0)
    after = (
        f'socket_open("127.0.0.1", {told.sockets[0].getsockname()[1]}, "test_socket")\n'
        'socket_send_line("after the loop", "test_socket")\nsleep(0.1)\ntextmsg("sleeping done.")\n'
    )
    try:
        await client.start(host, cell.config.ur.primary_port, after)
        # from the arm's own address, as from a UR's
        assert client.conns["reverse_socket"][1].get_extra_info("peername")[0] == host
        d = np.array([0.3, -0.2, 0.2, 0.1, -0.1, 0.4])
        points = [(Q0 + d * 0.5, d * 0.5), (Q0 + d, np.zeros(6))]
        client.send(
            "reverse_socket", REVERSE.pack(0, TrajectoryAction.RECEIVE, len(points), 0, 0, 0, 0, Mode.FORWARD)
        )
        for q, qd in points:
            client.send(
                "trajectory_socket",
                POINT.pack(*(round(v * M) for v in [*q, *qd]), *[0] * 6, M, 2, MotionType.SPLINE),
            )
        reader = client.conns["trajectory_socket"][0]
        async with asyncio.timeout(10):
            (result,) = RESULT.unpack(await reader.readexactly(4))
        assert result == Result.SUCCESS
        async with Bus.connect(cell.config.bus, "test") as bus:
            truth = await bus.subscribe("truth/r1")
            q = np.array((await truth.recv_messages(robot_pb2.RobotTruth))[-1].q)
        assert np.abs(q - (Q0 + d)).max() < 1e-3, q - (Q0 + d)
        # the target is where the program meant it to be, standing still: the last point exactly
        # (to the wire's 1e-6 rad), as a UR's target_q (the arm's own joints settle onto it)
        rtde = await asyncio.to_thread(
            rtde_receive.RTDEReceiveInterface, host, 125.0, ["target_q", "target_qd"]
        )
        assert np.abs(np.array(rtde.getTargetQ()) - (Q0 + d)).max() < 1e-6
        assert not np.any(rtde.getTargetQd())
        rtde.disconnect()
        # a secondary program runs beside it (the program goes on); one that would move is refused
        rtde = await asyncio.to_thread(
            rtde_receive.RTDEReceiveInterface, host, 125.0, ["actual_digital_output_bits"]
        )
        client.primary[1].write(b"sec setup():\n  set_standard_digital_out(3, True)\nend\n")
        client.primary[1].write(b"sec mover():\n  movej([0, -1.57, 1.57, -1.57, -1.57, 0])\nend\n")
        async with asyncio.timeout(5):
            await client.said(
                primary.RobotMessage.RUNTIME_EXCEPTION, b"a secondary program cannot move the arm"
            )
            while not rtde.getActualDigitalOutputBits() & (1 << 3):
                await asyncio.sleep(0.01)
        rtde.disconnect()
        client.send("reverse_socket", REVERSE.pack(0, 0, 0, 0, 0, 0, 0, Mode.IDLE))  # (still there)
        client.send("reverse_socket", REVERSE.pack(0, 0, 0, 0, 0, 0, 0, Mode.STOPPED))
        async with asyncio.timeout(5):  # the control loop ends: its sockets close, and what follows runs
            assert await client.conns["reverse_socket"][0].read() == b""
            assert await heard.get() == (host, b"after the loop\n")  # (closed as the program ended)
            await client.said(primary.RobotMessage.TEXT, b"sleeping done.")
            await client.said(primary.RobotMessage.KEY, b"PROGRAM_XXX_STOPPED")
    finally:
        client.close()
        told.close()


@pytest.mark.slow
async def test_a_missed_keepalive_ends_the_program_force_mode_is_refused_and_a_stop_is_c209(
    start_cell,
) -> None:
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=robots())
    host = cell.config.robots[0].ur_host
    client = Client()
    try:
        await client.start(host, cell.config.ur.primary_port)
        client.send("reverse_socket", REVERSE.pack(100, *(round(v * M) for v in Q0), Mode.SERVOJ))
        async with asyncio.timeout(5):  # nothing more within 100 ms: the program says so and ends
            await client.said(
                primary.RobotMessage.TEXT, b"Socket timed out waiting for command on reverse_socket"
            )
            assert await client.conns["reverse_socket"][0].read() == b""
        client.close()

        client = Client()
        await client.start(host, cell.config.ur.primary_port)
        client.send("script_command_socket", COMMAND.pack(Command.START_FORCE_MODE, *[0] * 27))
        async with asyncio.timeout(5):
            words = await client.said(primary.RobotMessage.RUNTIME_EXCEPTION, b"force_mode()")
            assert await client.conns["reverse_socket"][0].read() == b""
        line, _column = struct.unpack_from(">ii", words)
        assert line == 0
        client.close()

        # a protective stop (here a secondary program's) is reported as UR's error code C209A0
        client = Client()
        await client.start(host, cell.config.ur.primary_port)
        client.primary[1].write(b"sec stopper():\n  protective_stop()\nend\n")
        async with asyncio.timeout(5):
            words = await client.said(primary.RobotMessage.ERROR_CODE, b"protective stop")
            assert await client.conns["reverse_socket"][0].read() == b""  # (it stopped the program)
        code, argument, level = struct.unpack_from(">iii", words)
        assert (code, argument, level) == (209, 0, primary.ReportLevel.WARNING)  # (as a UR reports it)
    finally:
        client.close()


@pytest.mark.slow
async def test_two_clients_drive_two_arms_at_once_each_on_its_own_address(start_cell) -> None:
    """As two ROS 2 drivers would run against r1 and r2: each arm's program connects back to its
    own client, and each runs its own trajectory."""
    two = [{"id": i, "name": f"r{i}", "skill_port": free_port(), "backend": "kinematic", "truth_hz": 500}
           for i in (1, 2)]  # fmt: skip
    cell = await start_cell(run=["bus", "dataplane", "robots"], robots=two)
    clients = [Client(), Client()]
    try:
        for client, robot in zip(clients, cell.config.robots, strict=True):
            await client.start(robot.ur_host, cell.config.ur.primary_port)
            assert client.conns["reverse_socket"][1].get_extra_info("peername")[0] == robot.ur_host
        goals = [Q0 + np.array([0.2, 0, 0, 0, 0, 0]), Q0 + np.array([0, 0, 0, 0, 0, -0.3])]
        for client, goal in zip(clients, goals, strict=True):
            client.send(
                "reverse_socket", REVERSE.pack(0, TrajectoryAction.RECEIVE, 1, 0, 0, 0, 0, Mode.FORWARD)
            )
            client.send(
                "trajectory_socket",
                POINT.pack(*(round(v * M) for v in goal), *[0] * 12, M, 1, MotionType.SPLINE),
            )
        async with asyncio.timeout(10):
            for client in clients:
                (result,) = RESULT.unpack(await client.conns["trajectory_socket"][0].readexactly(4))
                assert result == Result.SUCCESS
        async with Bus.connect(cell.config.bus, "test") as bus:
            for name, goal in zip(("r1", "r2"), goals, strict=True):
                truth = await bus.subscribe(f"truth/{name}")
                q = np.array((await truth.recv_messages(robot_pb2.RobotTruth))[-1].q)
                assert np.abs(q - goal).max() < 1e-3, (name, q - goal)
    finally:
        for client in clients:
            client.close()
