"""The native data plane (cell/dataplane/native.c: the XDP program's C in user space) against the numpy
pipeline, record for record, and its packet path over real UDP sockets on loopback."""

from __future__ import annotations

import select
import threading

import numpy as np
import pytest

from cell.dataplane.native import NativeProgram, NativeServer, available
from cell.dataplane.tables import TP
from cell.dataplane.xdp.backend import XdpPipeline, XdpTables
from cell.robot import datagram, udp
from tests.dataplane.mapped import (
    Pair,
    check_gate_keeps_robots_heard,
    check_random_stream,
    load_random_trajectories,
    random_constants,
    statuses,
)

SRC = ("10.0.0.1", 40000)


def run_payload(program: NativeProgram, recs: np.ndarray) -> bytes:
    out = program.answer(recs.tobytes(), SRC)
    assert out is not None, "dropped"
    return out


def test_it_builds_here() -> None:
    assert available() == ""  # (the project installs cc: a build failure is a failure, never a skip)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_tables_and_statuses_give_bit_identical_commands_and_registers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    check_random_stream(Pair(random_constants(rng), NativeProgram, run_payload), rng)


def test_bad_records_drop_their_datagram_and_are_counted() -> None:
    rng = np.random.default_rng(5)
    pair = Pair(random_constants(rng), NativeProgram, run_payload)
    load_random_trajectories(pair, rng, 1_000_000_000)
    p = pair.program
    p.robots["joints"][1] = 6  # (as the data plane configures its robots: DataPlane.add_robot)
    good = statuses(rng, 1, [0, 1], 2)
    kind = good.copy()
    kind["kind"][1] = 1  # a command sent to the data plane
    joint = statuses(rng, 1, [0, 9], 2)  # robot 1 has 6 joints
    assert p.answer(kind.tobytes(), SRC) is None and p.answer(joint.tobytes(), SRC) is None
    assert p.answer(good.tobytes()[:30], SRC) is None  # not whole records
    out = p.answer(good.tobytes(), SRC)  # robot 1 is pinned to its first sender
    assert out is not None and datagram.view(bytearray(out))["kind"].tolist() == [1, 1]
    assert p.answer(good.tobytes(), ("10.0.0.9", 40000)) is None  # another sender for it: both spoofed
    c = p.counters()
    assert (c["rejected.kind"], c["rejected.joint"], c["rejected.length"], c["rejected.spoofed"]) == (
        1,
        1,
        1,
        2,
    )


def test_a_closed_gate_answers_with_the_last_commands_and_reads_no_table() -> None:
    rng = np.random.default_rng(6)
    pair = Pair(random_constants(rng), NativeProgram, run_payload)
    load_random_trajectories(pair, rng, 1_000_000_000)
    p = pair.program
    first = datagram.view(bytearray(run_payload(p, statuses(rng, 2, list(range(6)), 2))))
    gates = p.gates
    p.close_gate()
    try:
        held = datagram.view(bytearray(run_payload(p, statuses(rng, 2, list(range(6)), 3))))
    finally:
        p.open_gate()
    assert held["velocity"].tolist() == first["velocity"].tolist()
    assert p.counters()["held"] == 6 and p.gates == gates + 1


def test_a_robot_answered_at_the_gate_through_many_flips_keeps_its_plan() -> None:
    rng = np.random.default_rng(8)
    check_gate_keeps_robots_heard(Pair(random_constants(rng), NativeProgram, run_payload), rng)


class Plane:
    """A native program with one robot on a trajectory, served on a loopback socket."""

    def __init__(self) -> None:
        constants = random_constants(np.random.default_rng(7))
        self.program = NativeProgram(64, constants.n_bits, 6)
        self.tables = XdpTables(self.program)
        self.pipeline = XdpPipeline(self.tables, constants)
        self.tables.add_robot(1, 6)
        tps = [TP(1, 0, 0, 1.0, [0.5] * 6, [0.1] * 6)]
        self.tables.update(insert=tps, registers=[(1, 0, 1)])
        self.sock = udp.open_socket("127.0.0.1")
        udp.Sender(self.sock, datagram.SIZE)
        self.server = NativeServer(self.program, self.sock)
        self.robot = udp.open_socket("127.0.0.1")
        udp.Sender(self.robot, datagram.SIZE)

    def send(self, seq: int, joints: int = 6) -> None:
        recs = datagram.empty(joints)
        recs["robot_id"], recs["joint_id"], recs["kind"], recs["seq"] = 1, np.arange(joints), 0, seq
        self.robot.sendto(recs.tobytes(), self.sock.getsockname())

    def commands(self, timeout: float = 2.0) -> np.ndarray:
        out = []
        while len(out) < 6:
            ready, _, _ = select.select([self.robot], [], [], timeout)
            assert ready, f"{len(out)} commands answered, 6 expected"
            got = udp.recv_batch(self.robot)
            assert got is not None
            out += list(datagram.view(bytearray(got[0])))
        return np.array(out, datagram.DTYPE)

    def close(self) -> None:
        self.server.stop()
        self.sock.close()
        self.robot.close()


def test_a_gso_burst_of_statuses_is_answered_by_one_gso_burst_of_commands() -> None:
    plane = Plane()
    try:
        plane.send(1)
        assert plane.server.serve() == 1
        cmds = plane.commands()
        assert cmds["kind"].tolist() == [1] * 6 and sorted(cmds["joint_id"].tolist()) == list(range(6))
        assert (datagram.positions(cmds) == 0).all() and (datagram.velocities(cmds) > 0).all()
        c = plane.program.counters()
        assert c["packets"] == 6 and c["commands_out"] == 6 and c["datagrams"] == 1
        plane.robot.sendto(b"junk", plane.sock.getsockname())
        assert plane.server.serve() == 1 and plane.program.counters()["rejected.length"] == 1
    finally:
        plane.close()


def test_its_thread_answers_every_status_while_the_control_plane_flips_batches() -> None:
    """The server's own thread answers 300 statuses as they come, while this thread writes the tables
    behind the gate again and again: none is lost, each is a command, the gate was held."""
    plane = Plane()
    stop = threading.Event()

    def control_plane() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            tps = [TP(1, k % 4 + 1, 0, 0.5, [0.1 * (k % 5)] * 6, [0.0] * 6)]
            plane.tables.update(insert=tps, switches=[(1, 0, k % 4 + 1)])

    flipper = threading.Thread(target=control_plane)
    try:
        plane.server.start()
        flipper.start()
        for seq in range(1, 301):
            plane.send(seq)
            cmds = plane.commands()
            assert cmds["kind"].tolist() == [1] * 6
        stop.set()
        flipper.join(5)
        c = plane.program.counters()
        assert c["commands_out"] == 1800 and c["packets"] + c["held"] == 1800
        assert plane.program.gates > 0
        assert plane.server.counters()["native.answered"] == 1800
    finally:
        stop.set()
        plane.close()
