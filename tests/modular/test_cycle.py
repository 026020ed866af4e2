"""VDC in the running SnP cycle (cell.modular.cycle, and its C paths in cell/snp/master.c and cycle.c).

The C master must answer as the Python VdcMaster does, the C plant step as the Python Plant, and a
module must guess what does not come; end to end, a master and six modules in their own
processes move the MuJoCo arm along a reference over real UDP sockets."""

from __future__ import annotations

import ctypes
import random
import time

import numpy as np
import pytest

from cell.modular.cycle import SETTLE_NS, Plant, VdcMaster, VdcModule
from cell.modular.reference import CYCLE_NS, Q_HOME, joint_move
from cell.modular.wire import (
    A_LOCAL_QUERY,
    A_QUERY,
    B_LOCAL_REPLY,
    B_REPLY,
    C_QUERY,
    D_REPLY,
    b_of,
    b_values,
    ids_of,
    outboard_ids,
)
from cell.snp.link import Link, open_udp
from cell.snp.modular import CycleConfig, NodeState, Stage
from cell.snp.native import NativeCycles, NativeMaster, available
from cell.snp.packet import Configure, Configured, Denial, Denied, ModuleKind, NodeInfo, Pid, decode
from cell.timer import realtime_offset
from tests.conftest import run_unless_stolen, wait_until_quiet

native = pytest.mark.skipif(available() is not None, reason=f"the C cycle does not build: {available()}")
FAR = 10**18  # a deadline no run reaches
Q1 = Q_HOME + np.array([0.3, -0.2, 0.25, 0.2, -0.3, 0.4])


def move():
    return joint_move(Q_HOME, Q1, 1.5)


def a_query(j: int, qid: int, q: float, qd: float, t: int, deadline: int = FAR) -> bytes:
    (pos, vel), b_ids, _, _ = ids_of(j)
    return A_QUERY.pack(0, Pid.MRT, 900 + j, 0, qid, deadline, (pos, q, t, vel, qd, t),
                        tuple(x for k in b_ids for x in (k, t)))  # fmt: skip


def local_a_query(j: int, qid: int, q: float, qd: float, f_star: list[float], t: int) -> bytes:
    """A module computing its own [C, D]: A with its last F*, B and G wanted."""
    (pos, vel), b_ids, f_ids, _ = ids_of(j)
    f = tuple(x for k, v in zip(f_ids, f_star, strict=True) for x in (k, v, t))
    wanted = tuple(x for k in (*b_ids, *outboard_ids(j)) for x in (k, t))
    return A_LOCAL_QUERY.pack(0, Pid.MRT, 900 + j, 0, qid, FAR, (pos, q, t, vel, qd, t, *f), wanted)


def c_query(j: int, qid: int, f_star: list[float], t: int) -> bytes:
    _, _, f_ids, tau = ids_of(j)
    inputs = tuple(x for k, v in zip(f_ids, f_star, strict=True) for x in (k, v, t))
    return C_QUERY.pack(0, Pid.MRT, 900 + j, 0, qid, FAR, inputs, (tau, t))


class MasterRig:
    """A VdcMaster served by NativeMaster on a socket, a twin Python VdcMaster, and six sockets
    playing the modules (joint j: module j, in a chain)."""

    def __init__(self) -> None:
        self.sock = open_udp(timestamps=True)
        self.mods = [open_udp() for _ in range(6)]
        for s in self.mods:
            s.setblocking(True)
            s.settimeout(2.0)
        self.addrs = [s.getsockname() for s in self.mods]
        config = CycleConfig(period_ns=100_000_000, budget_ns=80_000_000)  # (no FDIR event in a test)
        ref = move()
        self.py, self.c = (VdcMaster(self.addrs, config, time.monotonic_ns, ref) for _ in range(2))
        now = time.monotonic_ns()
        for m in (self.py, self.c):
            for j, addr in enumerate(self.addrs):
                m._found(NodeInfo(100 + j, ModuleKind.JOINT, 99 + j if j else 0, 1), addr, now)
            for j, addr in enumerate(self.addrs):
                m._configured(Configured(j), addr, now)
            m.vdc.start_ns = now - 300 * CYCLE_NS  # (the reference 0.3 s on: moving)
            m.lost_ns = 10**12  # (no FDIR either: the first test's setup here may take its 50 ms)
        assert all(n.state == NodeState.INCLUDED for n in self.c.nodes.values())
        self.fast = NativeMaster(
            self.c, self.sock.fileno(), spin_ns=0, lead_ns=0, mono_of_real=realtime_offset()
        )
        self.c.fdir_here = False
        self.link = Link(self.sock)

    def exchange(self, j: int, data: bytes) -> tuple[bytes, bytes]:
        """(the C master's answer, the Python twin's) to module j's datagram."""
        self.mods[j].sendto(data, self.sock.getsockname())
        self.fast.push()
        handed = self.fast.run(time.monotonic_ns() + 5_000_000)
        assert handed is None, (handed, [n.state for n in self.c.nodes.values()])
        self.fast.pull(self.link)
        got = self.mods[j].recv(2048)
        out = self.py.receive(data, self.addrs[j], time.monotonic_ns()) + self.py.serve()
        return got, out[0][0]

    def close(self) -> None:
        for s in (self.sock, *self.mods):
            s.close()


@pytest.fixture
def master_rig():
    r = MasterRig()
    yield r
    r.close()


def _values(reply: bytes, shape) -> np.ndarray:  # type: ignore[no-untyped-def]
    f = shape.parse(reply)
    assert f is not None, reply
    return np.array(f[11::3][: shape.n])


@native
def test_the_c_master_answers_b_and_d_as_the_python_vdc_master(master_rig: MasterRig) -> None:
    t = time.monotonic_ns()
    rng = np.random.default_rng(5)
    q, qd = Q_HOME + rng.uniform(-0.05, 0.05, 6), rng.uniform(-0.3, 0.3, 6)
    for j in range(6):  # each joint's A in its slot: B from the recursion over those below
        c_b, py_b = master_rig.exchange(j, a_query(j, 10 + j, q[j], qd[j], t + 30_000 * j))
        b_c, b_py = _values(c_b, B_REPLY), _values(py_b, B_REPLY)
        assert np.allclose(b_c, b_py, rtol=1e-6, atol=1e-6), (j, b_c - b_py)
        assert abs(b_c).max() > 1.0  # (gravity in dV_r at least: not all zeros)
    forces = rng.uniform(-20, 20, (6, 6))
    for j in range(6):
        c_d, py_d = master_rig.exchange(j, c_query(j, 20 + j, list(forces[j]), t + 30_000 * j))
        assert np.allclose(_values(c_d, D_REPLY), _values(py_d, D_REPLY), rtol=1e-5, atol=1e-4)
    # D of the base joint carries every body's force out to the tip: not its own F* alone
    assert abs(_values(c_d, D_REPLY)[0] - forces[5][2]) < 1e-3  # (the last is the tip's own)
    assert master_rig.c.vdc.f_star[3] == pytest.approx(forces[3], rel=1e-6)  # pulled back
    h = master_rig.c.handler.counters
    assert (h.queries, h.replies) == (12, 12)


@native
def test_a_local_modules_b_and_g_from_the_c_master_match_the_python_vdc_master(master_rig: MasterRig) -> None:
    """Every module computing its own [C, D]: one query each, its last F* in, B and G out; its D
    (F* + G on its axis) is the master's own D from the same forces."""
    t = time.monotonic_ns()
    rng = np.random.default_rng(7)
    q, qd, forces = (
        Q_HOME + rng.uniform(-0.05, 0.05, 6),
        rng.uniform(-0.3, 0.3, 6),
        rng.uniform(-20, 20, (6, 6)),
    )
    g = np.zeros((6, 6))
    for j in reversed(range(6)):  # (tip first: each G then carries this round's outboard forces)
        c_r, py_r = master_rig.exchange(
            j, local_a_query(j, 40 + j, q[j], qd[j], list(forces[j]), t + 30_000 * j)
        )
        v_c, v_py = _values(c_r, B_LOCAL_REPLY), _values(py_r, B_LOCAL_REPLY)
        assert B_LOCAL_REPLY.parse(c_r)[10::3][20:26] == outboard_ids(j)  # type: ignore[index]
        assert np.allclose(v_c, v_py, rtol=1e-5, atol=1e-4), (j, v_c - v_py)
        g[j] = v_c[20:26]
    assert not g[5].any() and abs(g[0]).max() > 1.0  # the tip carries nothing; the base, the arm
    model = master_rig.py.vdc  # (its f_star: the forces as the wire rounded them)
    for j in range(6):
        assert float(model.f_star[j][2] + g[j][2]) == pytest.approx(model.tau_r(j), rel=1e-4, abs=1e-3)
    assert master_rig.c.vdc.f_star[2] == pytest.approx(forces[2], rel=1e-6)  # taken from the A


@native
@pytest.mark.parametrize("local", [False, True], ids=["a", "local-a"])
def test_a_vdc_query_with_another_joints_items_is_not_taken_as_its_a(
    master_rig: MasterRig, local: bool
) -> None:
    t = time.monotonic_ns()
    # joint 3's items, from joint 1's module
    forged = local_a_query(3, 5, 1.0, 0.0, [9.0] * 6, t) if local else a_query(3, 5, 1.0, 0.0, t)
    master_rig.mods[1].sendto(forged, master_rig.sock.getsockname())
    master_rig.fast.push()
    got = master_rig.fast.run(time.monotonic_ns() + 5_000_000)
    assert got is not None and got[1] == forged  # handed back to Python: not the fast path's
    assert master_rig.c.vdc.seq == [0] * 6 and master_rig.c.model.pos[3] == 0.0
    assert not master_rig.c.vdc.f_star[3].any()  # (nor its force)
    # and Python's master, handed it, does not take it: it denies it, saying why
    out = master_rig.c.receive(got[1], master_rig.addrs[1], time.monotonic_ns()) + master_rig.c.serve()
    assert len(out) == 1 and out[0][1] == master_rig.addrs[1]
    denied = decode(out[0][0]).body
    assert isinstance(denied, Denied) and denied.query_id == 5, denied
    # (joint 3's items are not joint 1's to give: its F* not one to take from it, B not one to give it)
    assert denied.explanation == (Denial.UNKNOWN_INPUT_ITEM if local else Denial.UNKNOWN_OUTPUT_ITEM)
    assert master_rig.c.vdc.seq == [0] * 6 and not master_rig.c.vdc.f_star[3].any()


@native
def test_the_c_plant_steps_the_arm_as_the_python_plant() -> None:
    t0 = 10**15
    py, c = (Plant(Q_HOME, clock=lambda: t0, capacity_s=1.0) for _ in range(2))
    cycles = NativeCycles(spin_ns=0, lead_ns=0, mono_of_real=0)
    cycles.drive(c)
    for p in (py, c):  # joints 1 and 2 driven, the others on their brakes
        p.tau[1], p.tau[2], p.driven[1], p.driven[2] = 40.0, -25.0, 1, 1
    end = t0 + 20 * CYCLE_NS + 100
    py.clock = lambda: end
    py.advance()
    cycles.lib.snp_plant_advance(ctypes.byref(cycles.plant), end)
    assert (c.arm.data.qpos == py.arm.data.qpos).all() and (c.arm.data.qvel == py.arm.data.qvel).all()
    assert (
        py.time.tolist() == c.time.tolist() == [t0 + 80 * py.dt_ns, t0 + 21 * CYCLE_NS, 21]
    )  # (the first at its first step)
    assert (py.rec_tool[:21] == c.rec_tool[:21]).all() and (py.rec_t[:21] == c.rec_t[:21]).all()
    moved = np.abs(py.arm.data.qpos - Q_HOME)
    assert moved[1] > 1e-3 and moved[2] > 1e-3  # driven
    assert moved[[0, 3, 4, 5]].max() < 2e-3  # braked (against gravity)


@native
def test_the_c_modules_adaptation_of_its_inertia_steps_as_the_python_modules() -> None:
    """VDC's parameter adaptation in cell/snp/cycle.c against cell.modular.vdc.Module's, a body 40 %
    light, over 50 cycles of a moving B: the same force and the same parameters, step by step."""
    from cell.modular.vdc import Gains

    plant = Plant(Q_HOME)
    cycles = NativeCycles(spin_ns=0, lead_ns=0, mono_of_real=0)
    cycles.drive(plant)
    py, c = (VdcModule(101, 0, plant, gains=Gains(adapt=100.0), believed=0.6) for _ in range(2))
    for m in (py, c):
        m.joint = 2
    assert cycles.plant is not None
    state = c.to_c(cycles.plant)
    rng = np.random.default_rng(3)
    f = np.zeros(6)
    start = py.dynamics().theta.copy()
    for _ in range(50):
        b = rng.uniform(-1, 1, 20)
        b[13] += 9.81  # (gravity in dV_r: what the missing mass shows in)
        want = py.dynamics().net_force(b_of(b), 0.001).f_star
        state.b[:] = b
        cycles.lib.snp_vdc_net_force(
            ctypes.byref(state), ctypes.c_double(0.001), f.ctypes.data_as(ctypes.c_void_p)
        )
        assert np.allclose(f, want, rtol=1e-9, atol=1e-9)
    theta = np.array(state.theta)
    assert np.allclose(theta, py.dynamics().theta, rtol=1e-9, atol=1e-12)
    assert np.abs(theta - start).max() > 0.1  # (it moved: the twins agree on a change)


def _module(plant: Plant, joint: int = 2, cd: str = "master") -> VdcModule:
    m = VdcModule(101, 0, plant, cd=cd)
    m.config = Configure(joint, 10_000_000, 0, 8_000_000, (20.0,))
    m.joint, m.state = joint, "running"
    m.next_start = 0
    return m


def test_a_module_guesses_a_b_that_does_not_come_and_drives_its_motor_with_d() -> None:
    plant = Plant(Q_HOME)
    m = _module(plant)
    a = m.poll(0)[0]  # its cycle starts at once (the servo reads raw as the master's time)
    f = A_QUERY.parse(a)
    assert f is not None and f[11:17:3] == ids_of(2)[0] and f[12] == pytest.approx(Q_HOME[2], abs=1e-3)
    _, b_ids, _, tau = ids_of(2)
    values = [0.5, 2.0, *[0.0] * 6, 0.0, 0.0, 0.0, 0.0, 0.0, 9.81, *[0.0] * 6]
    b = B_REPLY.pack(
        0, Pid.MRT, 0, 0, f[8], tuple(x for k, v in zip(b_ids, values, strict=True) for x in (k, v, 0))
    )
    corrupt = bytearray(b)
    corrupt[60] ^= 0xFF
    assert m.receive(bytes(corrupt), 1000) == []  # refused: its CRC (the cycle waits on)
    c = m.receive(b, 2000)[0]
    fc = C_QUERY.parse(c)
    assert fc is not None and fc[30] == tau and np.allclose(b_values(m.b), values, atol=1e-6)  # type: ignore[arg-type]
    assert fc[12:30:3][5] > 0  # F*_r holds its body up against gravity
    d = D_REPLY.pack(0, Pid.MRT, 0, 0, fc[8], (tau, 12.5, 0))
    assert m.receive(d, 3000) == [] and m.cycle is not None and m.cycle.stage == Stage.DONE
    assert plant.driven[2] == 1 and plant.tau[2] == pytest.approx(m.module.torque(12.5, m.b, m.qd))  # type: ignore[union-attr]
    # the next cycle's B never comes: at its deadline the last one, carried on, makes C
    m.next_start = 10_000_000
    m.poll(10_000_000)
    c2 = m.poll(10_000_000 + 4_000_001)
    assert m.missed[Stage.AB] == 1 and len(c2) == 1 and C_QUERY.parse(c2[0]) is not None
    assert m.b.qd_r == pytest.approx(0.5 + 2.0 * 0.01)  # type: ignore[union-attr]


def test_a_local_module_computes_its_own_d_in_one_exchange_and_sends_its_force_with_the_next_a() -> None:
    plant = Plant(Q_HOME)
    m = _module(plant, cd="local")
    f = A_LOCAL_QUERY.parse(m.poll(0)[0])
    assert f is not None and f[18:36:3] == (0.0,) * 6  # no force yet
    _, b_ids, _, _ = ids_of(2)
    values = [0.5, 2.0, *[0.0] * 11, 9.81, *[0.0] * 6, 1.0, -2.0, 3.0, 4.0, 5.0, -30.0]  # B, then G
    reply = B_LOCAL_REPLY.pack(0, Pid.MRT, 0, 0, f[8], tuple(
        x for k, v in zip(b_ids + outboard_ids(2), values, strict=True) for x in (k, v, 0)))  # fmt: skip
    assert m.receive(reply, 2000) == []  # no [C, D] to the master
    assert m.cycle is not None and m.cycle.stage == Stage.DONE and m.missed[Stage.AB] == 0
    want = m.module.net_force(m.b, 0.01).f_star  # type: ignore[union-attr, arg-type]
    assert m.tau_r == pytest.approx(want[2] + 3.0) and want[5] > 0  # F* + G on its axis
    assert plant.driven[2] == 1 and plant.tau[2] == pytest.approx(m.module.torque(m.tau_r, m.b, m.qd))  # type: ignore[union-attr]
    m.next_start = 10_000_000
    f2 = A_LOCAL_QUERY.parse(m.poll(10_000_000)[0])
    assert f2 is not None and np.allclose(f2[18:36:3], want, rtol=1e-6, atol=1e-5)  # its F* goes with A


def _b_and_g(joint: int, qid: int, g: list[float]) -> bytes:
    _, b_ids, _, _ = ids_of(joint)
    values = [0.5, 2.0, *[0.0] * 11, 9.81, *[0.0] * 6, *g]
    return B_LOCAL_REPLY.pack(0, Pid.MRT, 0, 0, qid, tuple(
        x for k, v in zip(b_ids + outboard_ids(joint), values, strict=True) for x in (k, v, 0)))  # fmt: skip


def test_a_neighbour_module_waits_for_its_outboard_neighbours_force_and_passes_its_own_inwards() -> None:
    from cell.modular.vdc import carried_force
    from cell.modular.wire import G_PASS

    plant = Plant(Q_HOME)
    m = _module(plant, joint=2, cd="neighbour")
    f = A_LOCAL_QUERY.parse(m.poll(0)[0])  # (the local query: its F* to the master, B and G back)
    assert f is not None
    assert m.receive(_b_and_g(2, f[8], [0.0, 0.0, 7.0, 0.0, 0.0, 0.0]), 1000) == []  # the master's G
    assert m.cycle is not None and m.cycle.stage == Stage.CD and m.cycle.qid == 0  # waits: cycle 0

    def g_pass(joint: int, cycle: int, g: list[float]) -> bytes:
        return G_PASS.pack(
            0,
            Pid.MRT,
            104,
            0,
            cycle,
            tuple(x for k, v in zip(outboard_ids(joint), g, strict=True) for x in (k, v, 0)),
        )

    nb = [1.0, -2.0, 3.0, 4.0, 5.0, -30.0]
    assert m.receive(g_pass(3, 0, nb), 2000) == [] and m.cycle.stage == Stage.CD  # another joint's G
    assert m.receive(g_pass(2, 7, nb), 2000) == [] and m.cycle.stage == Stage.CD  # another cycle's
    assert m.to_inboard == [] and (m.refused, m.late) == (1, 1)  # (each counted)
    assert m.receive(g_pass(2, 0, nb), 3000) == [] and m.cycle.stage == Stage.DONE
    force = m.f_star + np.array(nb, dtype=np.float32)
    assert (
        m.tau_r == pytest.approx(force[2]) and m.missed[Stage.CD] == 0
    )  # the neighbour's G, not the master's
    assert plant.driven[2] == 1
    # its own force, carried into joint 1's frame by its body at q (T1), passed to joint 1's module
    (sent,) = m.to_inboard
    p = G_PASS.parse(sent)
    assert p is not None and p[8] == 0 and p[10::3][:6] == outboard_ids(1)
    want = carried_force(plant.arm.bodies[2].transform(m.q), force)
    assert np.allclose(p[11::3][:6], want, rtol=1e-5, atol=1e-4)
    # the next cycle's G never comes: at its deadline the master's G stands in (counted)
    m.to_inboard.clear()
    m.next_start = 10_000_000
    f = A_LOCAL_QUERY.parse(m.poll(10_000_000)[0])
    m.receive(_b_and_g(2, f[8], [0.0, 0.0, 7.0, 0.0, 0.0, 0.0]), 10_001_000)  # type: ignore[index]
    assert m.poll(10_000_000 + 8_000_001) == [] and m.cycle.stage == Stage.DONE and m.missed[Stage.CD] == 1
    assert m.tau_r == pytest.approx(m.f_star[2] + 7.0) and len(m.to_inboard) == 1
    # the next cycle's G comes before its B (its neighbour ahead of it): kept, and taken as it waits
    m.to_inboard.clear()
    m.next_start = 20_000_000
    f = A_LOCAL_QUERY.parse(m.poll(20_000_000)[0])
    early = [0.5, 0.5, -4.0, 0.0, 0.0, 1.0]
    assert m.receive(g_pass(2, 2, early), 20_000_500) == [] and m.cycle.stage == Stage.AB
    m.receive(_b_and_g(2, f[8], [0.0, 0.0, 7.0, 0.0, 0.0, 0.0]), 20_001_000)  # type: ignore[index]
    assert m.cycle.stage == Stage.DONE and m.missed[Stage.CD] == 1  # (no wait: still the one before's)
    assert m.tau_r == pytest.approx(m.f_star[2] - 4.0) and len(m.to_inboard) == 1 and m.late == 1


def _whole_cycle(m: VdcModule, t: int, tau_r: float = 1.0) -> None:
    """One cycle of m from t, every exchange answered."""
    _, b_ids, _, tau = ids_of(m.joint)
    m.next_start = t
    a = A_QUERY.parse(m.poll(t)[0])
    values = [0.1, 0.0, *[0.0] * 11, 9.81, *[0.0] * 6]
    b = B_REPLY.pack(
        0, Pid.MRT, 0, 0, a[8], tuple(x for k, v in zip(b_ids, values, strict=True) for x in (k, v, t))
    )  # type: ignore[index]
    c = C_QUERY.parse(m.receive(b, t + 1000)[0])
    assert m.receive(D_REPLY.pack(0, Pid.MRT, 0, 0, c[8], (tau, tau_r, t)), t + 2000) == []  # type: ignore[index]


def test_a_module_whose_exchanges_keep_missing_brakes_its_joint_until_a_whole_cycle_comes() -> None:
    from cell.modular.cycle import SAFE_AFTER

    plant = Plant(Q_HOME)
    m = _module(plant)
    period, budget = m.config.period_ns, m.config.budget_ns  # type: ignore[union-attr]
    _whole_cycle(m, 0)
    assert plant.driven[2] == 1 and m.missed_run == 0
    for k in range(1, SAFE_AFTER + 1):  # nothing answers: each exchange guessed at its deadline
        t = k * period
        m.next_start = t
        assert len(m.poll(t)) == 1 and len(m.poll(t + budget // 2)) == 1  # A; then C on a guessed B
        m.poll(t + budget)  # D guessed: the cycle ends
        assert plant.driven[2] == (1 if k < SAFE_AFTER else 0), k
    assert m.braked == 1 and plant.hold[2] == plant.arm.data.qpos[2]  # on its brake where it stood
    _whole_cycle(m, (SAFE_AFTER + 1) * period, tau_r=2.0)
    assert plant.driven[2] == 1 and m.missed_run == 0 and plant.tau[2] != 0.0  # driven again


@pytest.mark.parametrize(
    ("in_c", "period_ns", "cd", "wrong"),
    [
        pytest.param(True, 1_000_000, ["master"] * 6, {}, marks=native, id="c-1ms"),
        pytest.param(True, 1_000_000, ["master"] * 3 + ["local"] * 3, {}, marks=native, id="c-1ms-mixed"),
        pytest.param(
            True, 1_000_000, ["local"] * 2 + ["neighbour"] * 4, {}, marks=native, id="c-1ms-neighbour"
        ),
        # (40 % light and not adapted: 3.4 mm off on the pick and place, `cell bench snp`)
        pytest.param(
            True,
            1_000_000,
            ["master"] * 6,
            {"believed": 0.6, "adapt": 100.0},
            marks=native,
            id="c-1ms-40pct-light-adapted",
        ),
        pytest.param(False, 4_000_000, ["local"] * 6, {}, id="python-4ms-local"),
    ],
)
@pytest.mark.slow
def test_a_master_and_six_modules_move_the_arm_along_the_reference_over_udp(
    in_c: bool, period_ns: int, cd: list[str], wrong: dict
) -> None:
    """In C at the slides' 1 ms; in Python at 4 ms (its modules' VDC costs about 0.9 ms a cycle: at
    1 ms it may miss, which `cell bench snp` shows).  Each module's [C, D] by the master or by itself
    (cd, base to tip); the modules' inertia wrong and adapted as they run (wrong)."""
    from cell.bench.snp_trial import SLOT_NS, cycle_figures, trial
    from cell.snp.runner import chain

    ref = move()
    seconds = 1.2 + SETTLE_NS / 1e9 + ref.t[-1]
    scale = period_ns // 1_000_000
    config = CycleConfig(period_ns=period_ns, budget_ns=period_ns, slot_ns=SLOT_NS * scale,
                         management_ns=400_000 * scale)  # fmt: skip
    slots = [{**s, "cd": where, **wrong} for s, where in zip(chain(6, random.Random(2)), cd, strict=True)]

    def run() -> tuple[dict, float]:
        # (seven processes' cycles on this machine's cores: not the last test's teardown)
        idle = wait_until_quiet()
        r = trial(slots, seconds, native=in_c, reference=ref, config=config)
        assert len(r["tool_error_mm"]) == len(ref.t)  # the whole reference ran, recorded every ms
        assert sorted(m["joint"] for m in r["modules"]) == list(range(6))
        h = r["master"]["handler"]
        assert h["replies"] + sum(v for k, v in h.items() if k.startswith("denied.")) == h["queries"]
        # a module computing its own [C, D] asks the master once a cycle, the master's twice
        asked = sum(len(m["cycles"]) * (1 if cd[m["joint"]] != "master" else 2) for m in r["modules"])
        # (cycles at the edges: a first one ended without its [C, D] before any B came, a last one's
        # query sent as the run ended; and an exchange missed in a stall may be a query the master
        # never had)
        missed = sum(int(np.asarray(m["cycles"])[:, 3].sum()) for m in r["modules"] if len(m["cycles"]))
        assert abs(h["queries"] - asked) <= 12 + missed, (asked, h["queries"], missed, f"{idle:.2f} idle")
        return r, idle

    def timing(out: tuple[dict, float]) -> str | None:
        # (the 2 mm aim of a clean cycle is `cell bench snp`'s, on a quiet machine; here a VM stall of a
        # few ms costs cycles now and then, which the modules guess across: the bound is issue 39's aim
        # for a lossy cycle, 5 mm; a fresh-clone run here saw 2.14 mm once, and 7.6 mm with the inertia
        # adapted on guessed cycles, which it no longer is.  The misses are the VM's stalls, every
        # module's at once: 0.5-5.5 % of exchanges on a quiet machine here, 9.5 % beside another
        # test's processes; the bound is a cycle that runs, the share a bench's figure: `cell bench
        # snp`.  A CI run once saw 46-73 % missed in all five cases, on an idle guest whose host ran
        # slow for a while: run_unless_stolen runs such a trial again)
        r, idle = out
        f, err = cycle_figures(r), r["tool_error_mm"]
        if f.modules_ran != 6 or err.max() >= 5.0 or f.missed_pct >= 15.0:
            ran = f"{f.modules_ran} modules ran, {err.max():.2f} mm"
            return f"{ran}, {f.missed_pct:.1f} % missed ({idle:.2f} cores idle before)"
        return None

    run_unless_stolen(run, timing)


def _c_module(plant: Plant, joint: int, period: int, cd: str = "master") -> tuple:
    """A VdcModule on its socket whose cycle runs in C (NativeCycles driving the plant): (its
    socket, the cycles, its C state, the module), configured, not pushed yet."""
    from cell.snp.tsp import Oscillator

    sock = open_udp(timestamps=True)
    cycles = NativeCycles(spin_ns=0, lead_ns=0, mono_of_real=realtime_offset())
    cycles.drive(plant)
    st = cycles.attach(sock.fileno(), Oscillator(0, 0.0, 0))
    m = _module(plant, joint, cd=cd)
    m.config = Configure(joint, period, 0, period * 4 // 5, (20.0,))
    return sock, cycles, st, m


@native
def test_the_c_module_asks_with_its_joint_answers_b_with_its_force_and_drives_its_motor_with_d() -> None:
    """A VDC module's cycle in C (cell/snp/cycle.c) against the Python VdcModule's arithmetic; a test
    socket plays the master."""
    import socket
    import threading

    from cell.modular.vdc import Gains, Module

    period, joint = 50_000_000, 2
    silent_cycles = 3  # after the first: then it goes on its brake (SAFE_AFTER)
    plant = Plant(Q_HOME)
    master = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    master.bind(("127.0.0.1", 0))
    master.settimeout(2.0)
    sock, cycles, st, m = _c_module(plant, joint, period)
    m.next_start = (time.monotonic_ns() // period + 1) * period
    cycles.push(st, m, master.getsockname())
    assert st.active and st.vdc
    until = m.next_start + period * (9 + 10 * silent_cycles) // 10
    loop = threading.Thread(target=cycles.run, args=([sock.fileno()], until), daemon=True)
    loop.start()
    try:
        a = A_QUERY.parse(master.recv(2048))
        assert a is not None and a[11:17:3] == ids_of(joint)[0] and a[18] == ids_of(joint)[1][0]
        # its joint as the plant has it (stepped to the A's time in C, untouched until B comes)
        assert a[12] == pytest.approx(plant.arm.data.qpos[joint], abs=1e-6)
        assert a[15] == pytest.approx(plant.arm.data.qvel[joint], abs=1e-6)
        _, b_ids, f_ids, tau = ids_of(joint)
        values = [0.4, -1.5, 0.1, 0.2, 0.3, 0.05, -0.02, 0.01, 0.5, -0.4, 0.3, 0.2, 1.0, 9.81, *[0.07] * 6]
        b = B_REPLY.pack(
            0,
            Pid.MRT,
            0,
            0,
            a[8],
            tuple(x for k, v in zip(b_ids, values, strict=True) for x in (k, v, a[13])),
        )
        sock_addr = sock.getsockname()
        master.sendto(b, sock_addr)
        c = C_QUERY.parse(master.recv(2048))
        assert c is not None and c[11:29:3] == f_ids and c[30] == tau
        got_b = B_REPLY.parse(b)
        twin = Module(plant.arm.bodies[joint], Gains())
        from cell.modular.wire import b_of

        want = twin.net_force(b_of(got_b[11::3][:20])).f_star  # type: ignore[index]
        assert np.allclose(c[12:30:3], want, rtol=1e-6, atol=1e-5)
        master.sendto(D_REPLY.pack(0, Pid.MRT, 0, 0, c[8], (tau, 7.5, a[13])), sock_addr)
        master.recv(2048)  # the next cycle's A: the first of those left unanswered
        torque = twin.torque(7.5, b_of(got_b[11::3][:20]), a[15])  # type: ignore[index]
        assert plant.driven[joint] == 1 and plant.tau[joint] == pytest.approx(torque, rel=1e-6)
        loop.join(5)
        assert not loop.is_alive()
        cycles.pull(st, m, Link(sock))
        assert m.missed == {"ab": silent_cycles, "cd": silent_cycles} and m.braked == 1
        assert plant.driven[joint] == 0  # on its brake: guesses in a row (VdcModule._drive's fail safe)
    finally:
        master.close()
        sock.close()


@native
def test_the_c_neighbour_module_keeps_a_g_come_before_its_b_and_passes_its_force_in_as_b_comes() -> None:
    """Its outboard neighbour ahead of it: this cycle's G comes before B.  C keeps it, ends the
    cycle as B comes (no wait for the deadline) and passes its force inwards, carried into the
    inboard module's frame, as VdcModule._pass_in does; a G of another cycle is counted late."""
    import socket
    import threading

    from cell.modular.vdc import carried_force
    from cell.modular.wire import G_PASS

    period, joint = 50_000_000, 2
    plant = Plant(Q_HOME)
    master, inboard = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    for s in (master, inboard):
        s.bind(("127.0.0.1", 0))
        s.settimeout(2.0)
    sock, cycles, st, m = _c_module(plant, joint, period, cd="neighbour")
    m.next_start = (time.monotonic_ns() // period + 1) * period
    cycle = m.next_start // period
    cycles.push(st, m, master.getsockname(), inboard.getsockname())
    assert st.active and st.vdc

    def g_pass(no: int, g: list[float]) -> bytes:
        items = tuple(x for k, v in zip(outboard_ids(joint), g, strict=True) for x in (k, v, 0))
        return G_PASS.pack(0, Pid.MRT, 104, 0, no & 0xFFFFFFFF, items)

    until = m.next_start + period // 2
    loop = threading.Thread(target=cycles.run, args=([sock.fileno()], until), daemon=True)
    loop.start()
    try:
        a = A_LOCAL_QUERY.parse(master.recv(2048))
        assert a is not None
        early = [0.5, 0.5, -4.0, 0.25, 0.0, 1.0]
        master.sendto(g_pass(cycle + 5, early), sock.getsockname())  # another cycle's: late
        master.sendto(g_pass(cycle, early), sock.getsockname())  # this cycle's, before B: kept
        # (one socket to one socket on loopback: they are read in the order sent)
        master.sendto(_b_and_g(joint, a[8], [0.0, 0.0, 7.0, 0.0, 0.0, 0.0]), sock.getsockname())
        passed = G_PASS.parse(inboard.recv(2048))
        loop.join(5)
        assert not loop.is_alive()
        cycles.pull(st, m, Link(sock))
    finally:
        for s in (master, inboard, sock):
            s.close()
    assert passed is not None and passed[8] == cycle & 0xFFFFFFFF
    assert passed[10::3][:6] == outboard_ids(joint - 1)  # (the inboard module's G ids)
    assert np.allclose(m.g, early) and m.missed == {"ab": 0, "cd": 0} and m.late == 1
    start, _, end, guessed = m.cycles[0]
    assert guessed == 0 and end - start < period // 4  # (ended as B came, not at its deadline)
    want = carried_force(plant.arm.bodies[joint].transform(m.q), m.f_star + np.array(early))
    assert np.allclose(passed[11::3][:6], want, rtol=1e-5, atol=1e-4)
