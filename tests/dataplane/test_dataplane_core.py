"""The data plane's tables and pipelines, sans IO: approximations, limits, stepping, switching, refusals."""

from __future__ import annotations

import gc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cell.dataplane.approx import LimitVelocity, TransformTable, bit_length, prefix_entries
from cell.dataplane.pipeline import (
    DROP_QUIET,
    DROP_UNDERRUN,
    DROP_WATCHDOG,
    QUIET_NS,
    STALL_DROP_NS,
    ControlConstants,
    Pipeline,
    reference_command,
)
from cell.dataplane.tables import TP, Refused, Tables, TPBatch
from cell.dataplane.wire import decode_keys, decode_tps, encode_keys, encode_tps
from cell.robot import datagram
from cell.robot.datagram import SCALE, Kind
from cell.v1 import dataplane_pb2

I64 = st.integers(-(2**63), 2**63 - 1)


@pytest.mark.parametrize("n", [4, 8, 12])
@pytest.mark.parametrize("c", [0.3, -0.7, 1.5, 0.0, 0.999])
def test_transform_error_within_the_bound(n: int, c: float) -> None:
    rng = np.random.default_rng(n)
    x = np.concatenate([rng.integers(-(2**45), 2**45, 50_000), rng.integers(-3000, 3000, 6000), [0, 1, -1]])
    t = TransformTable(c, n)
    exact = c * x.astype(np.float64)
    err = np.abs(t(x) - exact)
    # relative error 1/2^n (the paper's bound is 1/2^(n-1)), plus rounding to an integer
    assert np.all(err <= np.abs(exact) / 2**n + 1.0)
    assert t.entries == 2 * (2**n + (63 - n) * 2 ** (n - 1))


@settings(max_examples=300)
@given(y=st.lists(st.integers(0, 2**63 - 1), min_size=1, max_size=50))
def test_bit_length_is_exact_for_every_int64(y: list[int]) -> None:
    # float64 rounds values above 2^53; around powers of two that would be off by one
    edges = [(1 << k) + d for k in range(1, 63) for d in (-1, 0, 1)] + [0, 1, 2**63 - 1]
    values = np.array(y + edges, np.int64)
    assert bit_length(values).tolist() == [int(v).bit_length() for v in values.tolist()]


@settings(max_examples=300)
@given(x=I64, c=st.integers(0, 2**62 - 1))
def test_limit_velocity_is_exact(x: int, c: int) -> None:
    out = int(LimitVelocity(np.array([c]))(np.array([x]), np.array([0]))[0])
    assert out == max(-c, min(c, x))


def test_limit_entries_at_most_one_per_bit() -> None:
    for c in (0, 1, 1000, 33554432, 2**61 + 12345):
        hv, _, lv, _ = prefix_entries(c)
        assert hv.size <= 63 and lv.size <= 63
    hv, _, lv, _ = prefix_entries(0b1011)
    assert hv.size == 63 - 3  # one per 0 bit of c below the sign
    assert lv.size == bin((-0b1011) & (2**63 - 1)).count("1")


V_MAX = (np.pi,) * 6
CONSTANTS = ControlConstants(c1=(0.5,) * 6, c2=(2.0, 3.0, 4.0, 5.0, 6.0, 7.0), n_bits=8, v_max=V_MAX)


def status(robot: int, joint: int, v: float, p: float, seq: int = 1) -> np.ndarray:
    recs = datagram.empty(1)
    datagram.pack(recs, robot, joint, Kind.STATUS, seq, v, p)
    return recs


def batch(*parts: np.ndarray) -> np.ndarray:
    return np.concatenate(parts)


def hold_tp(robot: int, tp: int, nxt: int, q: list[float], dur: float = 0.1, joints: int = 6) -> TP:
    return TP(robot, tp, nxt, dur, q[:joints] + [0.0] * (joints - len(q[:joints])), [0.0] * joints)


@settings(max_examples=100, deadline=None)
@given(
    v=st.lists(I64, min_size=6, max_size=6),
    p=st.lists(I64, min_size=6, max_size=6),
    junk=st.integers(0, 2**32 - 1),
)
def test_no_input_and_no_table_contents_exceed_a_joint_limit(v: list[int], p: list[int], junk: int) -> None:
    tables = Tables(capacity=4)
    tables.add_robot(1)
    pipe = Pipeline(tables, CONSTANTS)
    rng = np.random.default_rng(junk)
    for bank in (pipe.transform_curr_velocity, pipe.transform_trg_velocity, pipe.transform_diff_position):
        bank.stack[:] = rng.integers(-(2**63), 2**63 - 1, bank.stack.shape, dtype=np.int64)
    tables.insert([hold_tp(1, 1, 1, [0.0] * 6)])
    tables.trg_vel[:] = rng.integers(-(2**63), 2**63 - 1, tables.trg_vel.shape, dtype=np.int64)
    tables.trg_pos[:] = rng.integers(-(2**63), 2**63 - 1, tables.trg_pos.shape, dtype=np.int64)
    tables.set_registers(1, 1, 0)
    recs = datagram.empty(6)
    recs["robot_id"], recs["joint_id"], recs["seq"] = 1, np.arange(6), 5
    recs["velocity"], recs["position"] = v, p
    pipe.process(recs, now=1)
    limit = np.rint(np.pi * SCALE)
    assert np.all(np.abs(recs["velocity"].astype(np.float64)) <= limit)
    assert np.all(recs["kind"] == Kind.COMMAND)


def test_integer_pipeline_matches_the_float_controller() -> None:
    rng = np.random.default_rng(7)
    tables = Tables(capacity=600)
    tables.add_robot(1)
    pipe = Pipeline(tables, CONSTANTS)
    rel = []
    for k in range(500):
        q_trg = rng.uniform(-3, 3, 6)
        v_trg = rng.uniform(-1, 1, 6)
        tables.insert([TP(1, k, k, 1.0, q_trg.tolist(), v_trg.tolist())])
        tables.set_registers(1, k, 10**18)
        v = rng.uniform(-2, 2, 6)
        p = q_trg + rng.uniform(-0.05, 0.05, 6) * rng.choice([1e-4, 1e-2, 1], 6)
        recs = datagram.empty(6)
        datagram.pack(recs, 1, np.arange(6), Kind.STATUS, k, v, p)
        pipe.process(recs, now=0)
        got = datagram.velocities(recs)
        for j in range(6):
            c1, c2 = CONSTANTS.c1[j], CONSTANTS.c2[j]
            ref = reference_command(v[j], p[j], v_trg[j], q_trg[j], c1, c2, np.pi)
            # each table term errs by at most 1/2^n of its size (+ fixed-point rounding)
            bound = (
                abs((1 - c1) * v[j]) + abs(c1 * v_trg[j]) + abs((c2 - 1) * (q_trg[j] - p[j]))
            ) / 2**8 + 1e-6
            assert abs(got[j] - ref) <= bound, (j, got[j], ref)
            if abs(ref) > 1e-3:
                rel.append(abs(got[j] - ref) / abs(ref))
    # the bound is per term; when terms nearly cancel the sum's relative error can be large
    assert np.median(rel) < 1 / 2**8


def steps_to(pipe: Pipeline, robot: int, now: int) -> int | None:
    pipe.process(batch(*(status(robot, j, 0.0, 0.0) for j in range(6))), now)
    return pipe.t.current_tp(robot)


def test_stepping_looping_and_additive_deadlines() -> None:
    t = Tables(capacity=16)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    # 10 -> 11 -> 12 -> 10 (a loop), 100 ms each
    t.insert([hold_tp(1, 10, 11, [0.1]), hold_tp(1, 11, 12, [0.2]), hold_tp(1, 12, 10, [0.3])])
    ms = 1_000_000
    t.set_registers(1, 10, 100 * ms)
    assert steps_to(pipe, 1, 50 * ms) == 10
    assert steps_to(pipe, 1, 100 * ms) == 11  # deadline reached: step
    assert t.reg_next_time[0] == 200 * ms  # additive: 100 ms + TP 11's 100 ms
    assert steps_to(pipe, 1, 150 * ms) == 11
    assert steps_to(pipe, 1, 250 * ms) == 12
    assert steps_to(pipe, 1, 330 * ms) == 10  # looped back
    assert t.reg_next_time[0] == 400 * ms  # never drifts with when packets come
    assert pipe.counters.stalls == 0


def test_one_step_per_packet_counts_resubmissions() -> None:
    t = Tables(capacity=16)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([hold_tp(1, i, i + 1, [0.0], dur=0.001) for i in range(10)] + [hold_tp(1, 10, 10, [0.0])])
    t.set_registers(1, 0, 0)
    pipe.process(batch(status(1, 0, 0, 0), status(1, 1, 0, 0), status(1, 2, 0, 0)), now=10**9)
    assert t.current_tp(1) == 3  # three packets: three steps, though far more were due
    assert pipe.counters.steps == 3 and pipe.counters.resubmits == 2


def test_tps_step_by_when_packets_arrived_not_when_they_were_processed() -> None:
    """A switch steps by its ingress timestamp; so does the pipeline given arrival times."""
    t = Tables(capacity=16)
    t.add_robot(1)
    t.add_robot(2)
    pipe = Pipeline(t, CONSTANTS)
    ms = 1_000_000
    for r in (1, 2):
        t.insert([hold_tp(r, 10, 11, [0.1]), hold_tp(r, 11, 11, [0.2])])
        t.set_registers(r, 10, 100 * ms)
    # processed at 101 ms: robot 1's statuses came in at 98.5 ms (before its deadline), robot 2's at 100.2
    recs = batch(*(status(r, j, 0.0, 0.0) for r in (1, 2) for j in range(6)))
    arrival = np.repeat([98 * ms + ms // 2, 100 * ms + ms // 5], 6).astype(np.int64)
    pipe.process(recs, 101 * ms, arrival=arrival)
    assert (t.current_tp(1), t.current_tp(2)) == (10, 11)
    pipe.process(batch(*(status(1, j, 0.0, 0.0) for j in range(6))), 101 * ms)  # no arrival: `now`
    assert t.current_tp(1) == 11


def test_the_kernel_stamps_each_burst_as_it_arrives() -> None:
    import time

    from cell.robot import udp

    rx, tx = udp.open_socket(timestamps=True), udp.open_socket()
    try:
        before = time.time_ns()
        tx.sendto(datagram.encode(datagram.Datagram(1, 0, Kind.STATUS, 1, 0.0, 0.0)), rx.getsockname())
        while (got := udp.recv_batch(rx)) is None:
            time.sleep(0.001)  # (polling a non-blocking socket, not synchronisation)
        stamped = got[3]
        assert before <= stamped <= time.time_ns()
        # a socket opened without them says 0
        rx.sendto(b"x" * datagram.SIZE, tx.getsockname())
        while (got := udp.recv_batch(tx)) is None:
            time.sleep(0.001)
        assert got[3] == 0
    finally:
        rx.close()
        tx.close()


def test_commands_steer_toward_the_current_tp() -> None:
    t = Tables(capacity=4)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([TP(1, 1, 1, 1.0, [0.5, 0, 0, 0, 0, -0.5], [0.0] * 6)])
    t.set_registers(1, 1, 10**18)
    recs = batch(*(status(1, j, 0.0, 0.0, seq=40 + j) for j in range(6)))
    pipe.process(recs, now=0)
    v = datagram.velocities(recs)
    assert v[0] == pytest.approx(2.0 * 0.5, rel=1 / 2**7)  # c2 (p_trg - p), c2 = 2
    assert v[5] == pytest.approx(-np.pi, abs=1e-6)  # 3.5 rad/s clamped to the limit
    assert recs["seq"].tolist() == list(range(40, 46))  # echoed
    assert list(recs["kind"]) == [Kind.COMMAND] * 6
    assert pipe.counters.limited == 1


def test_switching_to_an_alternate_trajectory() -> None:
    t = Tables(capacity=16)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([hold_tp(1, 1, 2, [0.1]), hold_tp(1, 2, 3, [0.2]), hold_tp(1, 3, 3, [0.3])])
    t.insert([hold_tp(1, 20, 21, [-0.1]), hold_tp(1, 21, 21, [-0.2])])  # the alternate branch
    t.set_registers(1, 1, 100)
    t.set_switch(1, 1, 20)  # after TP 1, take the branch
    assert steps_to(pipe, 1, 100) == 20
    assert steps_to(pipe, 1, 100 + 100_000_000) == 21
    t.unset_switch(1, 1)
    assert t.switch_row[t.row_of(1, 1)] == -1


def test_links_resolve_when_the_next_episode_arrives() -> None:
    t = Tables(capacity=16)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([hold_tp(1, 1, 2, [0.1])])  # TP 2 is not loaded yet
    t.set_registers(1, 1, 0)
    assert steps_to(pipe, 1, 10) == 1
    assert pipe.counters.stalls > 0  # due, but nowhere to go: holds TP 1
    t.insert([hold_tp(1, 2, 2, [0.2])])
    assert steps_to(pipe, 1, 20) == 2


def test_merged_robots_step_on_the_same_tick() -> None:
    t = Tables(capacity=16)
    t.add_robot(1)
    t.add_robot(2)
    e = t.merge([1, 2])
    assert t.entity_joints[e] == 12
    pipe = Pipeline(t, CONSTANTS)
    q = [float(i) / 100 for i in range(12)]
    t.insert([TP(1, 1, 2, 0.1, [0.0] * 12, [0.0] * 12), TP(2, 2, 2, 0.1, q, [0.0] * 12)])
    t.set_registers(2, 1, 1000)
    pipe.process(status(1, 0, 0, 0), now=1000)  # only robot 1 speaks: both move on
    assert t.current_tp(1) == t.current_tp(2) == 2
    recs = batch(status(2, 3, 0.0, 0.0))
    pipe.process(recs, now=1001)
    assert datagram.velocities(recs)[0] == pytest.approx(CONSTANTS.c2[3] * q[9], rel=1 / 2**7)


def test_unknown_and_idle_robots_are_told_to_hold() -> None:
    t = Tables(capacity=4)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([hold_tp(1, 1, 1, [3.0] * 6)])  # loaded (row 0) but robot 1 was never started on it
    recs = batch(status(1, 0, 1.0, 0.3), status(9, 0, 1.0, 0.3))
    pipe.process(recs, now=0)
    assert recs["velocity"].tolist() == [0, 0]
    assert pipe.counters.holds == 2
    assert pipe.counters.limited == 0  # a hold is not a limited command


def test_a_full_table_is_refused_with_a_reason_and_nothing_changes() -> None:
    t = Tables(capacity=3)
    t.add_robot(1)
    t.insert([hold_tp(1, 1, 1, [0.0]), hold_tp(1, 2, 2, [0.0])])
    with pytest.raises(Refused) as info:
        t.insert([hold_tp(1, 3, 3, [0.0]), hold_tp(1, 4, 4, [0.0])])
    assert info.value.code == "table_full" and "1 of 3 places free" in info.value.reason
    assert t.loaded == 2
    t.insert([hold_tp(1, 1, 1, [0.5]), hold_tp(1, 3, 3, [0.0])])  # replacing costs no place
    assert t.loaded == 3
    with pytest.raises(Refused, match="unknown_robot"):
        t.insert([hold_tp(7, 1, 1, [0.0])])


def test_deleting_a_tp_in_use_is_refused() -> None:
    t = Tables(capacity=8)
    t.add_robot(1)
    t.insert([hold_tp(1, 1, 2, [0.0]), hold_tp(1, 2, 3, [0.0]), hold_tp(1, 3, 3, [0.0])])
    t.set_registers(1, 1, 10**18)
    for busy in (1, 2):  # the current TP and the one it steps to
        with pytest.raises(Refused, match="in_use"):
            t.delete([(1, busy)])
    assert t.delete([(1, 3), (1, 99)]) == 1
    assert t.loaded == 2
    assert t.next_row[t.row_of(1, 2)] == -1  # its link waits for TP 3 again
    t.insert([hold_tp(1, 3, 3, [0.0])])
    assert t.next_row[t.row_of(1, 2)] == t.row_of(1, 3)


def test_a_batch_from_many_senders_is_answered_in_network_order() -> None:
    """Regression: np.concatenate turns big-endian structured fields native; batches must not."""

    from cell.config import load_config
    from cell.dataplane import plane as dataplane
    from cell.robot import udp
    from tests.conftest import cell_overrides

    cfg = load_config(
        overrides=cell_overrides(robots=[{"id": r, "name": f"r{r}", "skill_port": 100 + r} for r in (1, 2)])
    )
    plane = dataplane.DataPlane(cfg)
    socks = [udp.open_socket("127.0.0.1") for _ in range(2)]
    try:
        addr = plane.sock.getsockname()
        for robot, sock in zip((1, 2), socks, strict=True):
            for j in range(6):
                sock.sendto(
                    datagram.encode(datagram.Datagram(robot, j, Kind.STATUS, 300 + j, 0.1, 0.2)), addr
                )
        assert plane.handle() == 12
        for robot, sock in zip((1, 2), socks, strict=True):
            got = []
            while (r := udp.recv_batch(sock)) is not None:
                data, seg, _, _ = r
                got += [
                    datagram.decode(data[i : i + seg], kind=Kind.COMMAND) for i in range(0, len(data), seg)
                ]
            assert [(d.robot_id, d.joint_id, d.seq) for d in got] == [(robot, j, 300 + j) for j in range(6)]
            assert all(d.position == pytest.approx(0.2) for d in got)
    finally:
        plane.close()
        for s in socks:
            s.close()


def test_new_constants_swap_in_whole() -> None:
    t = Tables(capacity=4)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([TP(1, 1, 1, 1.0, [2.0] * 6, [0.0] * 6)])
    t.set_registers(1, 1, 10**18)
    recs = batch(status(1, 0, 0.0, 0.0))
    pipe.process(recs, now=0)
    assert datagram.velocities(recs)[0] == pytest.approx(np.pi, abs=1e-6)  # 2 rad x c2=2, limited at pi
    pipe.install(Pipeline.build(ControlConstants((1.0,) * 6, (0.25,) * 6, 8, (0.4,) * 6)))
    recs = batch(status(1, 0, 0.0, 0.0))
    pipe.process(recs, now=0)
    assert datagram.velocities(recs)[0] == pytest.approx(0.4, abs=1e-6)  # the new limit
    recs = batch(status(1, 0, 0.0, 1.0))
    pipe.process(recs, now=0)
    # the new gain: 0.25 = 1 + (c2 - 1), the (c2 - 1) p_diff term (-0.75) errs by at most 2^-8 of itself
    assert datagram.velocities(recs)[0] == pytest.approx(0.25, abs=0.75 / 2**8 + 1e-6)
    with pytest.raises(ValueError, match="v_max"):
        Pipeline.build(ControlConstants((1.0,) * 6, (1.0,) * 6, 8, (11.0,) * 6))


def test_a_key_named_twice_is_deleted_once_and_streaming_leaves_no_residue() -> None:
    t = Tables(capacity=64)
    t.add_robot(1)
    t.insert([hold_tp(1, i, i + 1, [0.0]) for i in range(10)])  # TP 9 waits for TP 10
    assert t.delete([(1, 3), (1, 3), (1, 4)]) == 2
    assert t.loaded == 8 and len(t._free) == 64 - 8  # no row freed twice
    t.insert([hold_tp(1, 100, 101, [0.0]), hold_tp(1, 101, 100, [0.0])])
    assert len({*t._free}) == len(t._free)
    # stream episodes through a small table: insert ahead, delete behind; nothing accumulates
    sizes = []
    for k in range(1, 40):
        t.insert([hold_tp(1, 1000 + 10 * k + i, 1000 + 10 * k + i + 1, [0.0]) for i in range(10)])
        t.delete([(1, 1000 + 10 * (k - 1) + i) for i in range(10)])
        sizes.append((len(t._waiting), sum(len(w) for w in t._waiting.values()), t.loaded))
    assert sizes[5] == sizes[-1]  # the same few open links (TP 2 -> 3, TP 9 -> 10, the live end), no growth
    assert sizes[-1][1] == 3


def run_sliced(t: Tables, pipe: Pipeline, robot: int, now: list[int], **update) -> list[int | None]:
    """A staged update with the packet path running between every two slices; the TPs it saw."""
    seen = []
    steps = t.staged_update(slice_size=4, **update)
    while True:
        now[0] += 1
        seen.append(steps_to(pipe, robot, now[0]))
        try:
            next(steps)
        except StopIteration:
            return seen


def test_a_staged_update_is_invisible_until_its_flip() -> None:
    t = Tables(capacity=128)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([hold_tp(1, i, i + 1, [0.0], dur=1e-9) for i in range(10)])  # TP 9 -> 10, not loaded yet
    t.set_registers(1, 0, 0)
    now = [0]
    for _ in range(12):
        now[0] += 1
        steps_to(pipe, 1, now[0])
    assert t.current_tp(1) == 9  # stalled at the end of the first episode
    episode = [hold_tp(1, 10 + i, 11 + i, [0.0], dur=1e-9) for i in range(40)]  # 10 slices of 4
    seen = run_sliced(t, pipe, 1, now, insert=episode, remove=[(1, i) for i in range(5)])
    flip = next(i for i, tp in enumerate(seen) if tp != 9)
    assert flip > 10  # many slices ran, and the robot stayed at TP 9 through all of them
    assert all(tp == 9 for tp in seen[:flip])
    assert all(tp is not None and tp >= 10 for tp in seen[flip:])  # then it moved on, into the new episode
    assert t.loaded == 10 + 40 - 5


def test_a_deletion_that_became_in_use_refuses_the_whole_update() -> None:
    t = Tables(capacity=64)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([hold_tp(1, 0, 1, [0.0], dur=1e-9), hold_tp(1, 1, 2, [0.0], dur=1e-9), hold_tp(1, 2, 2, [0.0])])
    t.set_registers(1, 0, 10**6)  # at TP 0 for now: deleting TP 2 looks safe when the update starts
    free_before, loaded_before = len(t._free), t.loaded
    steps = t.staged_update(
        insert=[hold_tp(1, 50 + i, 50 + i, [0.0]) for i in range(8)], remove=[(1, 2)], slice_size=2
    )
    next(steps)  # the update has started ...
    steps_to(pipe, 1, 10**6)  # ... and meanwhile the robot steps on, to TP 1 (next: TP 2)
    with pytest.raises(Refused, match="in_use"):
        for _ in steps:
            pass
    assert (len(t._free), t.loaded) == (free_before, loaded_before)  # the staged rows went back
    assert t.row_of(1, 2) >= 0 and not any(t.valid[r] for r in range(64) if t._key[r] & 0xFFFF_FFFF >= 50)
    with pytest.raises(Refused, match="unknown_tp"):
        t.row_of(1, 50)  # the staged keys left the index too


def test_an_abandoned_staged_update_gives_its_rows_back() -> None:
    t = Tables(capacity=32)
    t.add_robot(1)
    steps = t.staged_update(insert=[hold_tp(1, i, i, [0.0]) for i in range(20)], slice_size=4)
    for _ in range(8):  # checks done, part of the rows staged
        next(steps)
    steps.close()  # e.g. the request was cancelled
    assert len(t._free) == 32 and t.loaded == 0 and not t.valid.any() and not t._row
    t.insert([hold_tp(1, i, i, [0.0]) for i in range(32)])  # every place is usable again
    assert t.loaded == 32


def test_tp_columns_survive_the_wire_and_disagreeing_columns_are_refused() -> None:
    tps = [TP(1, 5, 6, 0.1, [0.5] * 6, [-0.5] * 6), TP(2, 6, 6, 0.2, list(np.arange(12) / 10), [0.0] * 12)]
    msg = dataplane_pb2.TableUpdate()
    encode_tps(TPBatch.of(tps), msg.insert)
    encode_keys([(1, 7), (3, 9)], msg.remove)
    back = dataplane_pb2.TableUpdate.FromString(msg.SerializeToString())
    got = decode_tps(back.insert)
    assert got.joints.tolist() == [6, 12] and got.positions.shape == (2, 12)
    assert got.positions[0, :6].tolist() == [0.5] * 6 and not got.positions[0, 6:].any()  # padded
    assert got.positions[1].tolist() == tps[1].positions and got.duration_s.tolist() == [0.1, 0.2]
    assert decode_keys(back.remove).tolist() == [[1, 7], [3, 9]]
    del back.insert.positions[-1]
    with pytest.raises(ValueError, match="18 joint values expected"):
        decode_tps(back.insert)
    del back.remove.id[-1]
    with pytest.raises(ValueError, match="2 robot ids, 1 TP ids"):
        decode_keys(back.remove)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 2e6])
def test_targets_that_are_not_finite_or_absurd_are_refused(bad: float) -> None:
    t = Tables(capacity=8)
    t.add_robot(1)
    with pytest.raises(Refused, match="not finite or out of range") as info:
        t.insert([hold_tp(1, 1, 1, [0.0]), TP(1, 2, 2, 0.1, [0.0] * 5 + [bad], [0.0] * 6)])
    assert info.value.code == "bad_request" and t.loaded == 0
    with pytest.raises(Refused, match="section duration"):
        t.insert([TP(1, 2, 2, float("nan"), [0.0] * 6, [0.0] * 6)])


def test_a_replaced_tp_never_links_to_a_tp_deleted_in_the_same_batch() -> None:
    t = Tables(capacity=16)
    t.add_robot(1)
    t.insert([hold_tp(1, 1, 2, [0.0]), hold_tp(1, 2, 2, [0.0]), hold_tp(1, 3, 3, [0.0])])
    t.update(insert=[hold_tp(1, 1, 3, [0.1])], remove=[(1, 3)])  # TP 1 now leads to TP 3, which goes
    assert t.next_row[t.row_of(1, 1)] == -1  # waits for TP 3 ...
    t.insert([hold_tp(1, 3, 3, [0.3])])
    assert t.next_row[t.row_of(1, 1)] == t.row_of(1, 3)  # ... and links when it is back


def test_an_update_gives_the_garbage_collector_no_work() -> None:
    """Per-TP objects the collector tracks (tuples as keys, say) would set off collections in the
    middle of an update, each a pause of the packet path that grows with the TPs loaded."""
    t = Tables(capacity=30_000)
    t.add_robot(1)

    def tps(first: int, n: int) -> TPBatch:
        ids, zeros = np.arange(first, first + n), np.zeros(n * 6)
        return TPBatch.from_flat(np.ones(n), ids, ids, np.ones(n), np.full(n, 6), zeros, zeros)

    t.insert(tps(0, 20_000))
    gc.collect()
    before = sum(s["collections"] for s in gc.get_stats())
    removed = t.update(insert=tps(100_000, 1_600), remove=np.stack([np.ones(10_000), np.arange(10_000)], 1))
    assert (removed, t.loaded) == (10_000, 11_600)
    assert sum(s["collections"] for s in gc.get_stats()) - before <= 1


def test_one_update_moves_a_robot_onto_new_tps_and_deletes_the_old_ones() -> None:
    """What a controller does to start a motion: load it, point the registers at it, drop the old."""
    t = Tables(capacity=16)
    t.add_robot(1)
    t.insert([hold_tp(1, 1, 1, [0.0])])
    t.set_registers(1, 1, 0)
    assert (
        t.update(
            insert=[hold_tp(1, 2, 3, [0.1]), hold_tp(1, 3, 3, [0.2])], registers=[(1, 2, 5)], remove=[(1, 1)]
        )
        == 1
    )
    assert t.current_tp(1) == 2 and t.loaded == 2 and int(t.reg_next_time[t.entity_of(1)]) == 5
    with pytest.raises(Refused, match="both started and deleted"):
        t.update(registers=[(1, 3, 0)], remove=[(1, 3)])


# --- faults: underruns, robots gone quiet ------------------------------------------------------------

MS = 1_000_000


def moving_tp(robot: int, tp: int, nxt: int, q: float, v: float, dur: float = 0.1) -> TP:
    return TP(robot, tp, nxt, dur, [q] * 6, [v] * 6)


def test_an_underrun_holds_the_tp_without_coasting_and_a_long_one_drops_the_trajectory() -> None:
    t = Tables(capacity=8)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([moving_tp(1, 1, 2, 0.5, 1.0)])  # moving at 1 rad/s toward 0.5; TP 2 never comes
    t.set_registers(1, 1, 10 * MS)
    recs = batch(*(status(1, j, 0.0, 0.5) for j in range(6)))
    pipe.process(recs, now=5 * MS)  # on time: the target velocity counts
    assert datagram.velocities(recs)[0] == pytest.approx(0.5 * 1.0, rel=1 / 2**7)  # c1 v_trg
    recs = batch(*(status(1, j, 0.0, 0.5) for j in range(6)))
    pipe.process(recs, now=20 * MS)  # due, nowhere to go: hold TP 1's position, target velocity 0
    assert t.reg_stalled[0] and t.current_tp(1) == 1
    assert np.abs(datagram.velocities(recs)).max() < 1e-6
    recs = batch(*(status(1, j, 0.0, 0.4) for j in range(6)))
    pipe.process(recs, now=20 * MS + STALL_DROP_NS + 1)  # stalled too long: the plan is gone
    assert t.current_tp(1) is None and t.reg_dropped_why[0] == DROP_UNDERRUN
    assert t.reg_dropped_ns[0] == 20 * MS + STALL_DROP_NS + 1
    assert datagram.velocities(recs).tolist() == [0.0] * 6  # it stands, not pulled to 0.5
    assert pipe.counters.dropped == 1


def test_a_short_underrun_resumes_when_the_tp_arrives() -> None:
    t = Tables(capacity=8)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    t.insert([moving_tp(1, 1, 2, 0.5, 1.0)])
    t.set_registers(1, 1, 10 * MS)
    assert steps_to(pipe, 1, 20 * MS) == 1 and t.reg_stalled[0]
    t.insert([moving_tp(1, 2, 2, 0.6, 0.0)])
    assert steps_to(pipe, 1, 30 * MS) == 2 and not t.reg_stalled[0]
    assert pipe.counters.dropped == 0


def test_a_robot_back_after_its_watchdog_finds_its_trajectory_dropped() -> None:
    t = Tables(capacity=8)
    for r in (1, 2, 3):
        t.add_robot(r)
    pipe = Pipeline(t, CONSTANTS)
    pipe.stale_periods[[1, 2, 3]] = 16  # (3 + 1) windows of 4 status periods
    pipe.quiet_ns[[1, 2, 3]] = QUIET_NS
    t.insert([moving_tp(r, 1, 1, 0.5, 0.0) for r in (1, 2, 3)])
    for r in (1, 2, 3):
        t.set_registers(r, 1, 10**18)
    pipe.process(
        batch(status(1, 0, 0, 0, seq=100), status(2, 0, 0, 0, seq=100), status(3, 0, 0, 0, seq=7)), MS
    )
    # robot 1 lived 17 periods without hearing us (its numbers jumped): its watchdog stopped it.
    # robot 2 was held up 60 ms and goes on with its next number: its watchdog never fired
    recs = batch(status(1, 0, 0.0, 0.0, seq=117), status(2, 0, 0.0, 0.0, seq=101), status(3, 0, 0, 0, seq=8))
    pipe.process(recs, now=60 * MS)
    assert t.current_tp(1) is None and t.current_tp(2) == 1 and t.current_tp(3) == 1
    assert t.reg_dropped_why[t.entity_of(1)] == DROP_WATCHDOG
    v = datagram.velocities(recs)
    assert v[0] == 0.0 and v[1] > 0.5  # robot 1 told to stand; robot 2 still pulled to its TP
    # a robot not heard for QUIET_NS (it, or we, hung): its plan is stale whatever its numbers say
    pipe.process(batch(status(3, 0, 0.0, 0.0, seq=9)), now=60 * MS + QUIET_NS + 1)
    assert t.current_tp(3) is None and t.reg_dropped_why[t.entity_of(3)] == DROP_QUIET


def test_the_sweep_drops_a_robot_that_went_quiet_without_a_packet() -> None:
    t = Tables(capacity=8)
    t.add_robot(1)
    pipe = Pipeline(t, CONSTANTS)
    pipe.quiet_ns[1] = QUIET_NS
    t.insert([moving_tp(1, 1, 1, 0.5, 0.0)])
    t.set_registers(1, 1, 10**18)
    pipe.process(status(1, 0, 0, 0), now=100 * MS)
    pipe.sweep(np.array([1]), 100 * MS + QUIET_NS)
    assert t.current_tp(1) == 1
    pipe.sweep(np.array([1]), 100 * MS + QUIET_NS + 1)
    assert t.current_tp(1) is None and t.reg_dropped_ns[0] == 100 * MS + QUIET_NS + 1


def test_keys_of_lists_every_tp_of_a_robots_entity() -> None:
    t = Tables(capacity=8)
    for r in (1, 2):
        t.add_robot(r)
    t.insert([hold_tp(1, 5, 6, [0.0]), hold_tp(1, 6, 6, [0.0]), hold_tp(2, 5, 5, [0.0])])
    assert sorted(t.keys_of(1)) == [(1, 5), (1, 6)]
    assert t.keys_of(2) == [(2, 5)]
    with pytest.raises(Refused):
        t.keys_of(3)
