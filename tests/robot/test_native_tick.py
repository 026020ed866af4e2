"""The robots' tick in C (cell/robot/tick.c) held to the Python model tick by tick.

Two groups of the same robots, one ticked in C and one in Python, each with a socket standing in for
its data plane, get the same datagrams at the same ticks (commands, junk, answers that come after
the status left), the same holds, programs and silences, and the same held-up ticks; after every
tick their statuses, drives and joints must be the same, bit for bit (C does numpy's operations in
numpy's order, without fused multiply-adds).
"""

from __future__ import annotations

import asyncio
import itertools
import socket
import time

import numpy as np
import pytest

from cell.config import load_config
from cell.robot import datagram, udp
from cell.robot.datagram import Datagram, Kind
from cell.robot.emulator import RobotGroup
from tests.conftest import cell_overrides

ROBOTS = 3


class Twin:
    """One robot group ticked in C and one in Python, and a data plane socket for each."""

    def __init__(self, backend: str, sockets: str) -> None:
        self.sinks = [udp.open_socket("127.0.0.1") for _ in range(2)]
        self.groups: list[RobotGroup] = []
        robots = [
            {"id": 10 + i, "name": f"t{i}", "skill_port": 3000 + i, "backend": backend, "socket": sockets}
            for i in range(ROBOTS)
        ]
        cfg = load_config(overrides={**cell_overrides(), "robots": robots})
        for sink, tick in zip(self.sinks, ("native", "python"), strict=True):
            host, port = sink.getsockname()
            g = RobotGroup(cfg.robots, f"{host}:{port}", tick=tick)
            self.groups.append(g)
            assert g.tick_impl == tick, g.tick_why  # (a C tick that does not build is a failure)

    def close(self) -> None:
        for g in self.groups:
            g.close()
        for s in self.sinks:
            s.close()

    def send(
        self,
        row: int,
        joints: list[int],
        v: list[float],
        robot_id: int | None = None,
        only: int | None = None,
    ) -> None:
        for k, (sink, g) in enumerate(zip(self.sinks, self.groups, strict=True)):
            if only is not None and k != only:
                continue
            addr = g.socks[0 if g.shared else row].getsockname()
            rid = int(g.ids[row]) if robot_id is None else robot_id
            for j, vj in zip(joints, v, strict=True):
                sink.sendto(datagram.encode(Datagram(rid, j, Kind.COMMAND, 0, vj, 0.0)), addr)

    def send_raw(self, row: int, data: bytes) -> None:
        for sink, g in zip(self.sinks, self.groups, strict=True):
            sink.sendto(data, g.socks[0 if g.shared else row].getsockname())

    def statuses(self, k: int) -> list[tuple]:
        out = []
        while (got := udp.recv_batch(self.sinks[k])) is not None:
            data, seg, _, _ = got
            assert seg == datagram.SIZE
            recs = datagram.view(data)
            out += [(int(r["robot_id"]), int(r["joint_id"]), int(r["seq"]), bytes(r.tobytes())) for r in recs]
        return sorted(out)


@pytest.fixture(params=[(b, s) for b in ("kinematic", "mujoco") for s in ("own", "shared")], ids="-".join)
def twin(request):
    t = Twin(*request.param)
    yield t
    t.close()


DRIVE_ARRAYS = (
    "velocity",
    "target",
    "pending",
    "has_pending",
    "missed",
    "stopped",
    "armed",
    "holds",
    "scripted",
    "servo_q",
    "servo_ff",
    "servo_since",
    "servo_tau",
)


def assert_same(t: Twin, got: list, tick: int) -> None:
    (c, p), (ec, ep) = t.groups, got
    assert [s.tolist() for s in ec] == [s.tolist() for s in ep], f"tick {tick}: stops and resumes"
    sc, sp = t.statuses(0), t.statuses(1)
    assert len(sc) == len(sp) and sc == sp, f"tick {tick}: the statuses differ"
    for name in DRIVE_ARRAYS:
        a, b = getattr(c.drives, name), getattr(p.drives, name)
        assert np.array_equal(a, b), f"tick {tick}: drives.{name} {a} != {b}"
    assert np.array_equal(c.backend.q, p.backend.q), f"tick {tick}: q"
    assert np.array_equal(c.backend.qd, p.backend.qd), f"tick {tick}: qd"
    assert c.tick_no == p.tick_no and c.state_time == p.state_time


def test_the_c_tick_does_what_the_python_tick_does_datagram_for_datagram(twin: Twin) -> None:
    rng = np.random.default_rng(53)
    late: list[tuple] = []  # commands to send as the next status has gone out (a kernel data plane's)

    def answerer(k: int):
        def answer_at_deadline() -> None:  # (to this group only: the other's status has not left)
            for row, joints, v in late:
                twin.send(row, joints, v, only=k)

        return answer_at_deadline

    for k, g in enumerate(twin.groups):
        g.at_deadline = answerer(k)
    stopped_seen = resumed_seen = servoed = 0
    for tick in range(420):
        late.clear()
        if tick % 4 == 1:  # each window: most robots commanded, some only partly, some not at all
            for row in range(ROBOTS):
                starve = (row == 0 and 40 <= tick < 80) or (row == 1 and 200 <= tick < 240)
                if starve:
                    continue
                joints = list(range(6)) if rng.random() > 0.1 else [int(j) for j in rng.choice(6, 3, False)]
                v = rng.uniform(-0.6, 0.6, len(joints)).tolist()
                twin.send(row, joints, v)
                if rng.random() < 0.3:  # a second command for some joints: the latest wins
                    twin.send(row, joints[:2], rng.uniform(-0.6, 0.6, len(joints[:2])).tolist())
        if tick % 8 == 4:  # an answer that comes as the status leaves: the next window's
            late.append((2, list(range(6)), rng.uniform(-0.3, 0.3, 6).tolist()))
        if tick % 37 == 0:  # junk: a status, a foreign robot, a joint too many, a short one, kind 3
            twin.send_raw(0, datagram.encode(Datagram(10, 1, Kind.STATUS, 0, 9.0, 0.0)))
            twin.send(1, [2], [9.0], robot_id=999)
            twin.send(2, [7], [9.0])
            twin.send_raw(1, b"short")
            twin.send_raw(0, bytes([0, 10, 1, 3]) + bytes(20))
        for g in twin.groups:  # what Python does to the drives between ticks, to both alike
            if tick == 100:
                g.drives.halt(np.array([1]))  # an e-stop on the Responsive Link
            if tick == 140:
                g.drives.halt(np.array([1]), on=False)
            if tick == 150:
                g.drives.script(2, True)  # a URScript program takes robot 2 over
            if 150 <= tick < 170:
                g.drives.target[2] = 0.2 * np.sin(np.arange(6) + tick / 10)
            if 170 <= tick < 190 and tick % 3 != 2:  # its servoj: targets as a late program sets them
                q = 0.1 * np.sin(np.arange(6) + tick / 10)
                g.drives.set_servo(2, q, q * 5, 0.004 if tick % 2 else 0.002, 0.1, extrapolate=tick > 180)
            if tick == 186:
                g.drives.halt(np.array([2]))  # (an e-stop in a servo: it brakes, the servo ends)
            if tick == 188:
                g.drives.halt(np.array([2]), on=False)
            if tick == 190:
                g.drives.script(2, False)
            if tick == 260:
                g.silent_until[0] = 1e18  # its cable pulled (`cell chaos`)
            if tick == 300:
                g.silent_until[0] = 0.0
        periods = 3 if tick == 330 else 150 if tick == 360 else 1  # held up: a little, then 0.3 s
        got = [g.tick(deadline=float("inf"), periods=periods) for g in twin.groups]
        stopped_seen += got[1][0].size
        resumed_seen += got[1][1].size
        assert_same(twin, got, tick)
        d = twin.groups[0].drives
        servoed += bool(d.servo_tau[2] > 0 and d.target[2].any() and d.servo_since[2] > 0.002)
    c, p = (g.counters.as_dict() for g in twin.groups)
    timing = ("lateness", "answer")
    assert {k: v for k, v in c.items() if not k.startswith(timing)} == {
        k: v for k, v in p.items() if not k.startswith(timing)
    }
    # the run did what it meant to: stops, resumes, rejects, programs' commands ignored, held ticks
    assert stopped_seen >= 3 and resumed_seen >= 2
    assert servoed >= 5  # ticks the drives ran a servo on past its feed-forward (t = 2 ms)
    counters = twin.groups[0].counters
    assert counters.rejected == {"length": 12, "kind": 24, "robot": 12, "joint": 12}
    assert counters.commands_ignored > 0 and counters.missed_ticks == 2 + 149
    assert twin.groups[0].drives.windows == twin.groups[1].drives.windows > 100


def test_the_c_tick_measures_the_loop_as_the_python_tick_does(twin: Twin) -> None:
    """The answers' histogram (each command's time from the status it answers to its arrival, kernel
    stamps): C adds to the group's own Lateness, which Python reads."""
    c = twin.groups[0]
    c.tick(deadline=float("inf"))
    for _ in range(5):
        twin.send(0, list(range(6)), [0.1] * 6)
        c.tick(deadline=float("inf"))
    h = c.counters.answers
    assert h.n == 30 and int(h.counts.sum()) == 30
    assert 0 < h.max_us < 1e6  # (kernel stamps: a real time since the status left)
    assert h.take_window()[0] == 30 and h.take_window()[0] == 0


@pytest.mark.parametrize("k", [0, 1], ids=["c", "python"])
def test_an_answer_is_timed_from_its_own_robots_status_not_the_groups_first(k: int) -> None:
    """A group's robots send one after another; each answer is timed from its own robot's status
    leaving (in the kernel a data plane answers each within microseconds of it), so a later robot's
    answers are not charged with the sends before it.  Here robot 0's status left 8 ms before the
    answers came and robot 1's 2 ms: the group's cutoff, 10 ms before, is neither's."""
    t = Twin("kinematic", "own")
    try:
        g = t.groups[k]
        g.tick(deadline=float("inf"))
        t.statuses(k)
        for row in (0, 1):
            t.send(row, list(range(6)), [0.1] * 6, only=k)
        at = time.time_ns()  # (loopback delivers within the send: every answer is stamped before this)
        g.sent_ns[0] = [at - 8_000_000, at - 2_000_000, 0]
        h = g.counters.answers
        before = h.counts.copy()
        if g.native is not None:
            g.native.after(at - 10_000_000, 1)
        else:
            g.receive(at - 10_000_000)
        us = np.repeat(np.arange(len(h.counts)), h.counts - before) * h.BIN_US
        assert len(us) == 12
        assert all(1000 <= v <= 2000 for v in us[:6]) and all(7000 <= v <= 8000 for v in us[6:]), us
    finally:
        t.close()


def test_a_full_socket_buffer_is_counted_not_fatal() -> None:
    """A data plane that never reads: the C tick counts what the kernel would not take."""
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sink.bind(("127.0.0.1", 0))
    host, port = sink.getsockname()
    robots = [{"id": 10, "name": "t0", "skill_port": 3000, "backend": "kinematic"}]
    cfg = load_config(overrides={**cell_overrides(), "robots": robots})
    g = RobotGroup(cfg.robots, f"{host}:{port}", tick="native")
    try:
        g.socks[0].setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        for _ in range(2000):
            g.tick(deadline=float("inf"))
        c = g.counters
        assert c.ticks == 2000 and c.status_sent + c.status_unsent == 2000 * 6
    finally:
        g.close()
        sink.close()


async def test_a_late_reader_of_the_ring_gets_every_tick_and_knows_the_newest() -> None:
    """run_native: C ticks in its own thread and Python reads the ring when it gets the CPU; a reader
    held up catches up on every tick it missed, each marked not live but the newest (RobotGroup.live:
    what a program's timeouts go by), and counted as a late read."""
    sink = udp.open_socket("127.0.0.1")
    host, port = sink.getsockname()
    robots = [{"id": 10, "name": "t0", "skill_port": 3000, "backend": "kinematic"}]
    cfg = load_config(overrides={**cell_overrides(), "robots": robots})
    g = RobotGroup(cfg.robots, f"{host}:{port}", tick="native")
    g.busy = lambda: True  # (every tick read, as for an RTDE client)
    seen: list[tuple[int, bool]] = []
    enough = asyncio.Event()

    def at_deadline() -> None:
        seen.append((g.tick_no, g.live))
        if len(seen) == 20:
            time.sleep(0.06)  # this reader held up for 30 ticks
        if len(seen) >= 100:
            enough.set()

    g.at_deadline = at_deadline
    try:
        async with asyncio.timeout(10), asyncio.TaskGroup() as tg:
            reader = tg.create_task(g.run_native())
            await enough.wait()
            reader.cancel()
        missed = g.counters.missed_ticks  # (periods C itself missed: a tick of several, one entry)
        late = g.counters.late_reads  # (wakes that found the reader 10 ms or more behind)
    finally:
        g.close()
        sink.close()
    ticks = [t for t, _ in seen]
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert min(gaps) == 1 and sum(gaps) - len(gaps) <= missed  # every tick C ticked, once, in order
    # the hold-up's 30 ticks, caught up on right after it, not live (a third of them at least, should
    # C itself miss some); the newest of each read is (whether the reader kept up before it is this
    # host's business: a read of two is no failure)
    assert sum(not live for _, live in seen[20:50]) >= 10
    assert seen[-1][1] is True
    assert late >= 1  # the hold-up, counted: what RTDE and servoj served late
