"""The joint modules' cycle in C (cell/snp/cycle.c via cell.snp.native), on real UDP sockets.

The C loop must put on the wire exactly what the Python JointModule would: its A and C are
compared byte by byte with the Python module's for the same state and answers.  A test socket
plays the master."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from cell.snp.link import Link, open_udp
from cell.snp.modular import _A, _ANSWER, _C, _IDS
from cell.snp.module import JointModule
from cell.snp.native import RUN_HANDED, RUN_UNTIL, NativeCycles, available
from cell.snp.packet import Configure, Denied, Header, Pid, encode
from cell.snp.tsp import Oscillator
from cell.timer import realtime_offset

pytestmark = pytest.mark.skipif(available() is not None, reason=f"the C cycle does not build: {available()}")

PERIOD, BUDGET = 50_000_000, 40_000_000  # long, so that the test's socket answers in time
RUN_FOR = PERIOD * 9 // 10  # one cycle, past its [C, D] deadline, short of the next one
JOINT, MODULE = 2, 101


def running(joint: int = JOINT) -> JointModule:
    """A Python module running its cycle, with a servo that reads the host's clock as it is."""
    m = JointModule(MODULE, 0, 1)
    m.config = Configure(joint, PERIOD, 0, BUDGET, (20.0,))
    m.joint, m.state = joint, "running"
    m.pos, m.vel = 0.25, -0.5
    # a whole period ahead at least: the C loop's thread is started after this, maybe late on a busy host
    m.next_start = (time.monotonic_ns() // PERIOD + 2) * PERIOD
    return m


class Rig:
    """One module's socket in the C loop (run in a thread, as a module process would), and a test
    socket that plays the master."""

    def __init__(self) -> None:
        self.master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.master.bind(("127.0.0.1", 0))
        self.master.settimeout(2.0)
        self.sock = open_udp(timestamps=True)
        self.addr = self.sock.getsockname()
        self.cycles = NativeCycles(spin_ns=0, lead_ns=0, mono_of_real=realtime_offset())
        self.state = self.cycles.attach(self.sock.fileno(), Oscillator(0, 0.0, 0))
        self.handed: list[bytes] = []
        self.thread: threading.Thread | None = None

    def start(self, m: JointModule, until: int) -> None:
        self.cycles.push(self.state, m, self.master.getsockname())
        assert self.state.active

        def loop() -> None:
            while (got := self.cycles.run([self.sock.fileno()], until)) is not None:
                if got[0] == RUN_HANDED:
                    self.handed.append(got[2])

        self.thread = threading.Thread(target=loop, daemon=True)
        self.thread.start()

    def recv(self) -> bytes:
        return self.master.recvfrom(2048)[0]

    def send(self, data: bytes) -> None:
        self.master.sendto(data, self.addr)

    def close(self) -> None:
        if self.thread is not None:
            self.thread.join(5)
        self.sock.close()
        self.master.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def answer(qid: int, item: int, value: float, t: int) -> bytes:
    """B or D as the master's fast path packs it."""
    return _ANSWER.pack(0, Pid.MRT, 0, MODULE, qid, (item, value, t))


def test_the_c_cycle_sends_the_python_modules_bytes_and_ends_in_its_state(rig: Rig) -> None:
    twin = running()  # the Python module, fed the same times and answers
    ids = _IDS[JOINT]
    m = running()
    m.next_start = twin.next_start  # (the same cycle, should a period boundary fall between the two)
    rig.start(m, until=twin.next_start + RUN_FOR)
    a = rig.recv()
    f = _A.parse(a)
    assert f is not None and f[1] == Pid.MRT and f[3] == MODULE and f[8] == 1  # qid 1
    t1 = f[13]
    assert f[9] == twin.next_start + BUDGET // 2  # the [A, B] deadline
    assert 0 <= t1 - twin.next_start < 20_000_000
    assert twin._start(twin.next_start, t1) == [a]  # byte for byte (the servo reads raw as is)

    b = answer(1, ids[2], 1.5, t1 + PERIOD)
    rig.send(b)
    c = rig.recv()
    assert twin.receive(b, t1 + 1000) == [c]
    fc = _C.parse(c)
    assert fc is not None and fc[8] == 2 and fc[11] == ids[3] and fc[12] == 5.0 * (1.5 - -0.5)

    d = answer(2, ids[4], -3.25, t1 + PERIOD)
    rig.send(d)
    assert twin.receive(d, t1 + 2000) == []
    rig.thread.join(5)  # type: ignore[union-attr]
    seen = JointModule(MODULE, 0, 1)  # what the C loop hands back
    link = Link(rig.sock)
    rig.cycles.pull(rig.state, seen, link)
    assert (seen.pos, seen.vel, seen.v_des, seen.torque) == (twin.pos, twin.vel, twin.v_des, twin.torque)
    assert seen.torque == -3.25 and seen.missed == {"ab": 0, "cd": 0} == twin.missed
    (rec,) = seen.cycles
    assert rec[:2] == twin.cycles[0][:2] == (twin.next_start, t1)
    assert rec[3] == 0 and rec[2] >= t1
    assert link.sent == 2 and rig.state.n_records == 0  # (taken, so zeroed in C)
    assert rig.handed == []


def test_a_denial_moves_on_at_once_and_an_unanswered_query_is_guessed_at_its_deadline(rig: Rig) -> None:
    m = running()
    rig.start(m, until=m.next_start + RUN_FOR)
    f = _A.parse(rig.recv())
    assert f is not None
    sent = time.monotonic_ns()
    rig.send(encode(Header(0, Pid.MRT, b"", 0, MODULE), Denied(f[8], 1)))
    fc = _C.parse(rig.recv())  # [C, D] right after the denial, long before [A, B]'s deadline
    assert fc is not None and time.monotonic_ns() - sent < BUDGET // 2
    assert fc[12] == 5.0 * (m.v_des - m.vel)  # no new desired velocity: the last one stands
    rig.send(answer(f[8], _IDS[JOINT][2], 9.0, 0))  # a late B (A's query id): counted, not taken
    # C is never answered: guessed at its deadline, the cycle recorded with both exchanges missed
    rig.thread.join(5)  # type: ignore[union-attr]
    assert rig.state.late == 1
    seen = JointModule(MODULE, 0, 1)
    rig.cycles.pull(rig.state, seen, Link(rig.sock))
    (rec,) = seen.cycles
    assert rec[3] == 2 and seen.missed == {"ab": 1, "cd": 1}
    assert rec[2] - rec[0] >= BUDGET  # ended at the [C, D] deadline
    assert seen.v_des == 0.0 and seen.torque == 0.0


def test_junk_and_broken_answers_are_handed_back_untouched_and_do_not_end_the_exchange(rig: Rig) -> None:
    m = running()
    rig.start(m, until=m.next_start + RUN_FOR)
    f = _A.parse(rig.recv())
    assert f is not None
    good = answer(f[8], _IDS[JOINT][2], 1.0, 0)
    bad_crc = good[:-1] + bytes([good[-1] ^ 0xFF])
    junk = [b"", b"\x00", bad_crc, good[:-1], b"\xf0" * 40, bytes(range(200))]
    for j in junk:
        rig.send(j)
    rig.send(good)
    assert _C.parse(rig.recv()) is not None  # the good B, after all the junk, answered [A, B]
    rig.thread.join(5)  # type: ignore[union-attr]
    assert rig.handed == junk  # each handed to Python as it came (empty datagrams included)
    assert rig.state.missed_ab == 0


def test_the_run_returns_on_time_with_nothing_running() -> None:
    sock = open_udp(timestamps=True)
    try:
        cycles = NativeCycles(spin_ns=0, lead_ns=0, mono_of_real=0)
        cycles.attach(sock.fileno(), Oscillator(0, 0.0, 0))
        t0 = time.monotonic_ns()
        assert cycles.run([sock.fileno()], t0 + 30_000_000) is None
        assert 30_000_000 <= time.monotonic_ns() - t0 < 1_000_000_000
    finally:
        sock.close()
    assert RUN_UNTIL == 0
