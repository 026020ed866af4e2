"""The egress port (cell.dataplane.egress), sans IO: wire times, strict priority, tail drop; and the
data plane forwarding ordinary traffic through it."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cell.config import load_config, parse_host_port
from cell.dataplane.egress import BULK, OVERHEAD, ROBOT, EgressPort
from cell.dataplane.plane import DataPlane
from cell.robot import datagram, udp
from cell.robot.datagram import Kind
from tests.conftest import free_port

RATE = 8e6  # 8 Mbit/s: one byte a microsecond
BULK_SEG = 100 - OVERHEAD  # a 100-byte frame: 100 us on the wire
ROBOT_SEG = 24  # a command: 70 bytes, 70 us


class Wire:
    """What the port hands to the kernel, with the (virtual) time it was handed over at."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, int, tuple]] = []  # (time, datagrams, address)
        self.now = 0

    def send(self, data: memoryview, seg: int, addr: tuple) -> int:
        n = len(data) // seg
        self.sent.append((self.now, n, addr))
        return n


def at(port: EgressPort, wire: Wire, t_us: int) -> int | None:
    wire.now = t_us * 1000
    return port.transmit(wire.now)


def test_a_packet_leaves_when_its_wire_time_has_passed_and_a_run_at_the_line_rate() -> None:
    port, wire = EgressPort(RATE, 10_000, "fifo"), Wire()
    assert port.enqueue(BULK, bytes(10 * BULK_SEG), BULK_SEG, ("b", 1), wire.send, 0) == 10
    assert wire.sent == []  # the first frame is still on the wire
    assert at(port, wire, 99) == 1000  # ns until it has gone
    assert at(port, wire, 350) == 50_000
    assert wire.sent == [(350_000, 3, ("b", 1))]  # three frames of 100 us each by 350 us
    assert at(port, wire, 2000) is None
    assert sum(n for _, n, _ in wire.sent) == 10
    assert port.bytes_sent == 1000 and port.backlog() == 0
    # the wire was idle from 1000 us: a frame queued at 5000 us starts then, not back at 1000 us
    port.enqueue(BULK, bytes(BULK_SEG), BULK_SEG, ("b", 1), wire.send, 5_000_000)
    assert at(port, wire, 5099) == 1000


@pytest.mark.parametrize("scheduling", ["fifo", "priority"])
def test_a_robot_command_waits_behind_the_backlog_in_a_fifo_and_goes_next_under_priority(scheduling) -> None:
    port, wire = EgressPort(RATE, 10_000, scheduling), Wire()
    port.enqueue(BULK, bytes(10 * BULK_SEG), BULK_SEG, ("b", 1), wire.send, 0)
    at(port, wire, 350)  # three frames gone, the fourth on the wire (300-400 us)
    port.enqueue(ROBOT, bytes(6 * ROBOT_SEG), ROBOT_SEG, ("r", 2), wire.send, 350_000)
    at(port, wire, 5000)
    robot = port.counters[ROBOT]
    if scheduling == "fifo":
        assert robot.delays_ns == [650_000]  # behind the seven frames left: starts at 1000 us
    else:
        assert robot.delays_ns == [50_000]  # after the frame on the wire: starts at 400 us
    assert robot.sent == 6
    # the six commands went as one run, between the bulk frames under priority, after them in a fifo
    order = [addr[0] for _, _, addr in wire.sent]
    assert order[-1] == ("r" if scheduling == "fifo" else "b")


def test_priority_sends_bulk_frames_only_up_to_a_waiting_robot_packet() -> None:
    """A late wake-up must not send bulk frames that, on the wire, come after a robot packet."""
    port, wire = EgressPort(RATE, 10_000, "priority"), Wire()
    port.enqueue(BULK, bytes(10 * BULK_SEG), BULK_SEG, ("b", 1), wire.send, 0)
    port.enqueue(ROBOT, bytes(ROBOT_SEG), ROBOT_SEG, ("r", 2), wire.send, 250_000)  # 3rd frame on the wire
    at(port, wire, 2000)
    first_robot = next(i for i, (_, _, a) in enumerate(wire.sent) if a[0] == "r")
    assert (
        sum(n for _, n, _ in wire.sent[:first_robot]) == 3
    )  # the two gone by 250 us and the one on the wire
    assert port.counters[ROBOT].delays_ns == [50_000]


@pytest.mark.parametrize("scheduling", ["fifo", "priority"])
def test_a_full_buffer_drops_what_does_not_fit_and_counts_it(scheduling) -> None:
    port, wire = EgressPort(RATE, 500, scheduling), Wire()  # five 100-byte frames
    assert port.enqueue(BULK, bytes(8 * BULK_SEG), BULK_SEG, ("b", 1), wire.send, 0) == 5
    taken = port.enqueue(ROBOT, bytes(6 * ROBOT_SEG), ROBOT_SEG, ("r", 2), wire.send, 0)
    assert port.counters[BULK].dropped == 3
    if scheduling == "fifo":  # one buffer for both: the robot's commands are lost
        assert taken == 0 and port.counters[ROBOT].dropped == 6
    else:  # a queue of its own
        assert taken == 6 and port.counters[ROBOT].dropped == 0
    at(port, wire, 10_000)
    assert port.backlog() == 0
    s = port.summary()
    assert s["bulk_sent"] == 5 and s["bulk_dropped"] == 3


def test_a_port_needs_a_rate_and_a_buffer() -> None:
    with pytest.raises(ValueError, match="rate and a buffer"):
        EgressPort(0, 100, "fifo")


async def test_the_data_plane_forwards_ordinary_traffic_through_its_port_and_answers_robots_first() -> None:
    """Real sockets on loopback: 100 datagrams into a forwarding rule at once against an 8 Mbit/s port
    with a 2 KiB buffer; a robot's status meanwhile.  What fits is forwarded intact and in order, the
    rest is dropped and counted, and the robot is answered from its own queue."""
    sink = udp.open_socket("127.0.0.1", 0, gro=False)
    gen = udp.open_socket("127.0.0.1", 0, gro=False)
    rob = udp.open_socket("127.0.0.1", 0, gro=False)
    fwd = f"127.0.0.1:{free_port()}"
    cfg = load_config(
        overrides={
            "robots": [{"id": 1, "name": "r1", "skill_port": free_port()}],
            "dataplane": {
                "listen": f"127.0.0.1:{free_port()}",
                "forward": [{"listen": fwd, "to": f"127.0.0.1:{sink.getsockname()[1]}"}],
                "egress": {"rate_mbps": 8.0, "buffer_kb": 2.0, "scheduling": "priority"},
            },
        }
    )
    plane = DataPlane(cfg)
    loop = asyncio.get_running_loop()
    try:
        async with asyncio.timeout(10), asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(plane.run()), tg.create_task(plane.pump())]
            for i in range(100):
                gen.sendto(i.to_bytes(2, "big") + bytes(198), parse_host_port(fwd))
            status = datagram.empty(6)
            datagram.pack(status, 1, np.arange(6), Kind.STATUS, 7, 0.0, 0.0)
            for rec in status:  # a robot's six datagrams
                rob.sendto(rec.tobytes(), plane.sock.getsockname())
            commands = datagram.view(b"".join([await loop.sock_recv(rob, 4096) for _ in range(6)]))
            assert (
                len(commands) == 6
                and (commands["kind"] == Kind.COMMAND).all()
                and (commands["seq"] == 7).all()
            )
            f = plane.forwarders[0]
            while f.received < 100 or plane.egress.backlog():  # everything read and the port drained
                await asyncio.sleep(0.005)
            for t in tasks:
                t.cancel()
        got = []
        while (x := udp.recv_batch(sink)) is not None:
            got.append(x[0])
        counters = plane.counters()
    finally:
        plane.close()
        for s in (sink, gen, rob):
            s.close()
    assert f.received == 100 and 0 < f.dropped < 100 and f.sent + f.dropped == 100
    assert len(got) == f.sent == counters["egress.bulk_sent"]
    seq = [int.from_bytes(d[:2], "big") for d in got]
    assert seq == sorted(seq) and all(len(d) == 200 for d in got)  # intact, in order
    assert counters["egress.robot_sent"] == 6 and counters["egress.robot_dropped"] == 0
    assert counters["egress.bulk_dropped"] == f.dropped
