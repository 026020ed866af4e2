"""The master's side of the cycle in C (cell/snp/master.c via cell.snp.native.NativeMaster), on
real UDP sockets.

Its answers must be the Python master's, byte for byte: a twin Python `Master` in the same state
takes the same queries, and B, D and denials are compared.  Test sockets play the modules."""

from __future__ import annotations

import socket
import time

import pytest

from cell.snp.link import Link, open_udp
from cell.snp.master import Master
from cell.snp.modular import _A, _C, _IDS, CycleConfig, NodeState
from cell.snp.native import RUN_EVENT, RUN_HANDED, NativeMaster, available
from cell.snp.packet import Configured, ModuleKind, NodeInfo, Pid
from cell.snp.runner import Slot, run_modules
from cell.timer import realtime_offset
from tests.conftest import snp_master_on_loopback

pytestmark = pytest.mark.skipif(available() is not None, reason=f"the C cycle does not build: {available()}")

PERIOD, BUDGET = 10_000_000, 8_000_000
FAR = 10**18  # a deadline no run reaches


class Rig:
    """A master socket served by NativeMaster, a twin Python master, and one socket per module."""

    def __init__(self, joints: int = 2, **master_kw: int) -> None:
        self.sock = open_udp(timestamps=True)
        self.mods = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(joints)]
        for s in self.mods:
            s.bind(("127.0.0.1", 0))
            s.settimeout(2.0)
        self.addrs = [s.getsockname() for s in self.mods]
        config = CycleConfig(period_ns=PERIOD, budget_ns=BUDGET, slot_ns=1_000_000)
        self.py, self.c = (Master(self.addrs, config, time.monotonic_ns, **master_kw) for _ in range(2))
        self.c.model.t0 = self.py.model.t0
        now = time.monotonic_ns()
        for m in (self.py, self.c):  # found and configured as a chain: module j is joint j
            for j, addr in enumerate(self.addrs):
                m._found(NodeInfo(100 + j, ModuleKind.JOINT, 100 + j - 1 if j else 0, 1), addr, now)
            for j, addr in enumerate(self.addrs):
                m._configured(Configured(j), addr, now)
        assert all(n.state == NodeState.INCLUDED for n in self.c.nodes.values())
        self.fast = NativeMaster(
            self.c, self.sock.fileno(), spin_ns=0, lead_ns=0, mono_of_real=realtime_offset()
        )
        self.c.fdir_here = False
        self.link = Link(self.sock)

    def send(self, j: int, data: bytes) -> None:
        self.mods[j].sendto(data, self.sock.getsockname())

    def run(self, for_ns: int = 20_000_000) -> tuple | None:
        self.fast.push()
        got = self.fast.run(time.monotonic_ns() + for_ns)
        self.fast.pull(self.link)
        return got

    def recv(self, j: int) -> bytes:
        return self.mods[j].recvfrom(2048)[0]

    def close(self) -> None:
        for s in (self.sock, *self.mods):
            s.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def a_query(j: int, qid: int, pos: float, vel: float, t: int, deadline: int = FAR) -> bytes:
    ids = _IDS[j]
    inputs = (ids[0], pos, t, ids[1], vel, t)
    return _A.pack(0, Pid.MRT, 900 + j, 0, qid, deadline, inputs, (ids[2], t + PERIOD))


def c_query(j: int, qid: int, force: float, t: int, deadline: int = FAR) -> bytes:
    ids = _IDS[j]
    return _C.pack(0, Pid.MRT, 900 + j, 0, qid, deadline, (ids[3], force, t), (ids[4], t + PERIOD))


def python_answers(rig: Rig, j: int, data: bytes) -> list[bytes]:
    """What the Python master answers (its fast path and handler) to a module's datagram."""
    out = rig.py.receive(data, rig.addrs[j], time.monotonic_ns())
    return [d for d, _ in out + rig.py.serve()]


def test_the_c_master_answers_a_and_c_with_the_python_masters_bytes(rig: Rig) -> None:
    t = time.monotonic_ns()
    sent = [
        (0, a_query(0, 1, 0.3, -0.2, t)),
        (1, a_query(1, 7, -0.6, 0.9, t + 1_000)),
        (0, c_query(0, 2, 1.5, t)),  # D needs both joints' positions (gravity on the links above)
        (1, c_query(1, 8, -2.25, t + 1_000)),
    ]
    for j, data in sent:
        rig.send(j, data)
        assert rig.run(5_000_000) is None
        got = rig.recv(j)
        assert got == python_answers(rig, j, data)[0]
        assert got[14] == 2 and len(got) == 40  # a reply, not a denial
    model_c, model_py = rig.c.model, rig.py.model
    for j in (0, 1):  # the inputs taken into the arm model, pulled back into the Python master
        assert (model_c.pos[j], model_c.vel[j], model_c.at[j], model_c.force[j]) == (
            model_py.pos[j], model_py.vel[j], model_py.at[j], model_py.force[j],
        )  # fmt: skip
    h = rig.c.handler.counters
    assert (h.queries, h.replies) == (4, 4)
    assert rig.link.sent == 4


def test_a_query_that_cannot_be_met_is_denied_as_the_python_master_denies_it(rig: Rig) -> None:
    t = time.monotonic_ns()
    data = a_query(0, 5, 0.1, 0.1, t, deadline=t - 1)
    rig.send(0, data)
    assert rig.run(5_000_000) is None
    got = rig.recv(0)
    assert got == python_answers(rig, 0, data)[0]
    assert got[14] == 3 and got[20] == 1  # DENIAL, DEADLINE_CANNOT_BE_MET
    assert rig.c.handler.counters.denied["deadline_cannot_be_met"] == 1
    assert rig.c.model.at[0] != t  # a denied query's inputs are not taken


def test_everything_else_is_handed_back_untouched_and_the_path_goes_on(rig: Rig) -> None:
    t = time.monotonic_ns()
    good = a_query(0, 1, 0.3, -0.2, t)
    bad_crc = good[:-1] + bytes([good[-1] ^ 0xFF])
    wrong_item = a_query(1, 3, 0.1, 0.1, t)  # joint 1's items, from joint 0's module
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for data, frm in ((bad_crc, 0), (wrong_item, 0), (b"", 0), (b"\x00" * 80, 0)):
            rig.send(frm, data)
            got = rig.run()
            assert got is not None and got[0] == RUN_HANDED and got[1] == data and got[3] == rig.addrs[frm]
        stranger.sendto(good, rig.sock.getsockname())  # a good A from an address no module holds
        got = rig.run()
        assert got is not None and got[0] == RUN_HANDED and got[1] == good
    finally:
        stranger.close()
    rig.send(0, good)  # and the fast path still answers
    assert rig.run(5_000_000) is None
    assert rig.recv(0) == python_answers(rig, 0, good)[0]
    assert rig.c.handler.counters.replies == 1


def test_fdir_in_c_guesses_reports_silent_takes_back_and_excludes() -> None:
    rig = Rig(joints=1, suspect_cycles=2, lost_ns=60_000_000)
    try:
        node = rig.c.nodes[rig.addrs[0]]
        rig.send(0, a_query(0, 1, 0.0, 0.0, time.monotonic_ns()))
        assert rig.run(2_000_000) is None and rig.recv(0)
        got = rig.run(40_000_000)  # no more A's: two cycles guessed, then reported silent
        assert got is not None and got[0] == RUN_EVENT
        assert node.state == NodeState.SUSPECT and rig.c.events[-1][1:] == ("silent", 100, 0)
        assert rig.c.counters.guessed == 2
        rig.send(0, a_query(0, 2, 0.0, 0.0, time.monotonic_ns()))  # it comes back
        got = rig.run(5_000_000)
        assert got is not None and got[0] == RUN_EVENT
        assert node.state == NodeState.INCLUDED and rig.c.events[-1][1] == "back"
        assert rig.recv(0)  # (answered too)
        t = time.monotonic_ns()
        while (got := rig.run(200_000_000)) is not None and node.state != NodeState.LOST:
            assert got[0] == RUN_EVENT  # silent again, then excluded: lost_ns after it was heard
        assert node.state == NodeState.LOST and rig.c.counters.lost == 1
        assert 40_000_000 < time.monotonic_ns() - t < 150_000_000
        assert not rig.c.model.active[0] and rig.c.events[-1][1] == "lost"
        rig.send(0, a_query(0, 3, 0.0, 0.0, time.monotonic_ns()))  # excluded: no longer the fast path's
        got = rig.run()
        assert got is not None and got[0] == RUN_HANDED
    finally:
        rig.close()


@pytest.mark.parametrize(
    ("native_master", "native_modules"),
    [(False, True), (True, False), (True, True)],
    ids=["python-master-c-modules", "c-master-python-modules", "c-master-c-modules"],
)
def test_master_and_modules_on_loopback_one_plugged_in_and_one_pulled_out(
    native_master: bool, native_modules: bool
) -> None:
    # (a C loop releases the GIL while it waits, so the other side's thread runs meanwhile)
    with snp_master_on_loopback(3, native=native_master) as (master, ports):
        slots = [
            Slot(21, 0, ports[0], offset_ns=1_000_000, drift_ppm=30.0),
            Slot(22, 21, ports[1], offset_ns=-800_000, drift_ppm=-30.0, unplug_s=1.4),
            Slot(23, 22, ports[2], offset_ns=500_000, plug_s=0.6),
        ]
        run_modules(slots, seconds=2.0, spin=False, native=native_modules)
    first, pulled, late = (s.module for s in slots)
    assert first is not None and pulled is not None and late is not None
    assert (first.joint, pulled.joint, late.joint) == (0, 1, 2)
    assert len(first.cycles) > 1000 and 400 < len(pulled.cycles) < 1400 and len(late.cycles) > 300
    assert late.cycles[0][0] > pulled.cycles[0][0] + 400_000_000  # included while the cycle ran
    for s in slots:
        m = s.module
        assert m is not None
        in_cycles = sum(c[3] for c in m.cycles)
        assert in_cycles <= sum(m.missed.values()) <= in_cycles + 2  # (one may have been cut off)
        assert s.clock_errors and abs(s.clock_errors[-1]) < 1_000_000  # servoed (up to 1 ms off)
        assert s.link is not None and s.link.sent >= 2 * len(m.cycles)  # (a C loop's sends counted too)
    assert [e[1] for e in master.events if e[2] == 22][-2:] == ["silent", "lost"]
    h = master.handler.counters
    # every query answered or denied (how many meet their deadline is `cell bench snp`'s figure)
    assert (
        h.queries > 3000 and h.replies > 0 and h.replies + h.denied["deadline_cannot_be_met"] >= h.queries - 1
    )
    assert master.counters.beacons > 100 and master.counters.guessed > 0
