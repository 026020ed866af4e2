"""The differential rig of the data plane's programs (the XDP program, the native data plane in C)
against the numpy pipeline: the same tables and statuses, bit-identical commands and registers."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cell.dataplane.pipeline import DROP_WATCHDOG, ControlConstants, Pipeline
from cell.dataplane.tables import NO_ROW, TP, Tables
from cell.dataplane.xdp.backend import XdpPipeline, XdpTables
from cell.robot import datagram


class Pair:
    """A numpy pipeline and a program of mapped tables (the XDP program, the native data plane), given
    the same control-plane calls; `run(program, records)` is the program's answer to records."""

    def __init__(self, constants: ControlConstants, make: Callable, run: Callable, capacity=512) -> None:
        self.program = make(capacity, constants.n_bits, len(constants.c1))
        self.run = run
        self.xt = XdpTables(self.program)
        self.xp = XdpPipeline(self.xt, constants)
        self.nt = Tables(capacity, 1024, 12)
        self.np = Pipeline(self.nt, constants)

    def both(self, fn: str, *args: object, **kwargs: object) -> None:
        for obj in (self.nt, self.xt) if hasattr(self.nt, fn) else (self.np, self.xp):
            getattr(obj, fn)(*args, **kwargs)

    def close(self) -> None:
        self.program.close()

    def packet(self, recs: np.ndarray, now: int) -> tuple[np.ndarray, np.ndarray]:
        """The commands each pipeline makes of these records at `now`."""
        ours = recs.copy()
        self.np.process(ours, now, arrival=np.full(recs.size, now, np.int64))
        self.program.globals["clock_ns"] = now
        return ours, datagram.view(bytearray(self.run(self.program, recs)))

    def registers(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        n = self.nt.entities
        names = ("tp", "next_time", "stalled", "stall_ns", "dropped_ns", "dropped_why")
        out = {k: (getattr(self.nt, f"reg_{k}")[:n], getattr(self.xt, f"reg_{k}")[:n]) for k in names}
        for k in ("status_pos", "status_vel", "status_ns", "status_seq"):
            out[k] = (getattr(self.nt, k), getattr(self.xt, k))
        return out


def random_constants(rng: np.random.Generator) -> ControlConstants:
    return ControlConstants(
        tuple(rng.uniform(0.2, 1.5, 6).round(3)),
        tuple(rng.uniform(0.5, 40, 6).round(3)),
        int(rng.integers(4, 11)),
        tuple(rng.uniform(0.3, 4, 6).round(3)),
    )


def load_random_trajectories(pair: Pair, rng: np.random.Generator, t0: int) -> None:
    """Robots 1-6 alone, 7+8 merged; chains of TPs (a loop, a hold, a missing link), switches."""
    for r in range(1, 7):
        pair.both("add_robot", r)
    for t in (pair.nt, pair.xt):
        t.merge([7, 8])
    for r in range(1, 9):  # stale after 3 periods' jump, quiet after 40 ms
        pair.np.stale_periods[r] = pair.xp.stale_periods[r] = 3
        pair.np.quiet_ns[r] = pair.xp.quiet_ns[r] = 40_000_000
    for robot, joints in ((1, 6), (2, 6), (3, 6), (4, 6), (5, 6), (6, 6), (7, 12)):
        n = int(rng.integers(3, 20))
        ends = rng.choice(["loop", "hold", "missing"])
        tps = []
        for i in range(n):
            nxt = i + 1
            if i == n - 1:
                nxt = {"loop": 0, "hold": i, "missing": 999}[ends]
            tps.append(
                TP(
                    robot,
                    i,
                    nxt,
                    float(rng.choice([0.0005, 0.001, 0.002, 0.004, 0.008])),
                    rng.normal(0, 2, joints).tolist(),
                    rng.normal(0, 1.5, joints).tolist(),
                )
            )
        switches = [(robot, int(rng.integers(0, n)), int(rng.integers(0, n)))] if rng.random() < 0.5 else []
        start = t0 + int(rng.integers(0, 3e6))
        pair.both("update", insert=tps, switches=switches, registers=[(robot, 0, start)])


def statuses(rng: np.random.Generator, robot: int, joints: list[int], seq: int) -> np.ndarray:
    recs = datagram.empty(len(joints))
    recs["robot_id"], recs["joint_id"], recs["kind"], recs["seq"] = robot, joints, 0, seq
    scale = rng.choice([1e-3, 1.0, 1e3, 1e9])  # small, usual, large, clamped by INPUT_LIMIT
    recs["velocity"] = np.clip(rng.normal(0, 1, len(joints)) * scale * datagram.SCALE, -9e18, 9e18)
    recs["position"] = np.clip(rng.normal(0, 2, len(joints)) * scale * datagram.SCALE, -9e18, 9e18)
    return recs


def check_random_stream(pair: Pair, rng: np.random.Generator) -> None:
    """The same random stream through both: bit-identical commands, registers and counters."""
    try:
        t = 1_000_000_000
        load_random_trajectories(pair, rng, t)
        seqs = dict.fromkeys(range(1, 12), 1)
        stepped = limited = 0
        for k in range(3000):
            gaps = [50_000, 300_000, 1_000_000, 2_000_000, 60_000_000]  # 60 ms: past the quiet bound
            t += int(rng.choice(gaps, p=[0.3, 0.3, 0.3, 0.09, 0.01]))
            robot = int(rng.choice([1, 2, 3, 4, 5, 6, 7, 8, 11]))  # 11: not configured (held at 0)
            seqs[robot] += 1 if rng.random() > 0.02 else int(rng.integers(2, 50))  # some watchdog jumps
            size = int(rng.choice([1, 2, 6, 6]))
            joints = sorted(rng.choice(6, size, replace=False).tolist())
            recs = statuses(rng, robot, joints, seqs[robot])
            if rng.random() < 0.1:  # a GSO batch mixing two robots
                other = int(rng.choice([1, 7, 8]))
                seqs[other] += 1
                more = statuses(rng, other, [0, 1, 2], seqs[other])  # (concatenate would make them native)
                recs = datagram.view(bytearray(recs.tobytes() + more.tobytes()))
            if k % 500 == 250:
                pair.both("stop", [3, 7, 8])
            if k % 500 == 400:
                pair.both("stop", [3, 7, 8], False)
            if k % 150 == 0:  # the controller sets the registers again (dropped trajectories restart)
                for r in (1, 2, 3, 4, 5, 6, 7):
                    tp = int(rng.integers(0, 3))
                    pair.both("update", registers=[(r, tp, t + int(rng.integers(0, 2e6)))])
            if k % 700 == 0:
                pair.both("set_stop_ramp", rng.uniform(1, 20, 6).tolist(), 0.008)
            ours, theirs = pair.packet(recs, t)
            assert theirs.tobytes() == ours.tobytes(), f"packet {k}: {ours} != {theirs}"
            if k % 100 == 0:
                for name, (a, b) in pair.registers().items():
                    assert np.array_equal(a, b), f"{name} differs after packet {k}"
        kernel = pair.program.counters()
        c = pair.np.counters
        names = ("packets", "holds", "steps", "resubmits", "stalls", "limited", "stop_commands", "dropped")
        for name in names:
            assert kernel[name] == getattr(c, name), name
        stepped, limited = c.steps, c.limited
        # the stream exercised what it is meant to: steps, resubmissions, limits, stalls, drops, stops
        assert stepped > 100 and c.resubmits > 0 and limited > 0 and c.stalls > 0
        assert c.dropped > 0 and c.stop_commands > 0 and c.holds > 0
    finally:
        pair.close()


def check_gate_keeps_robots_heard(pair: Pair, rng: np.random.Generator) -> None:
    """Statuses answered at a closed gate were heard: a robot held there for more periods than its
    watchdog allows (a fleet's updates back to back) is not judged at its next status to have lived
    without us, and its plan goes on; the statuses it never sent still count."""
    try:
        load_random_trajectories(pair, rng, 1_000_000_000)  # (stale after a jump of 3 periods)
        p, ent = pair.program, int(pair.xt.robot_entity[2])
        pair.packet(statuses(rng, 2, list(range(6)), 2), 1_000_000_000)
        assert pair.xt.reg_tp[ent] != NO_ROW and pair.xt.status_seq[2] == 2
        for seq in range(3, 13):  # ten periods, each at a gate closed for a flip
            p.close_gate()
            try:
                pair.run(p, statuses(rng, 2, list(range(6)), seq))
            finally:
                p.open_gate()
        assert pair.xt.status_seq[2] == 12
        pair.packet(statuses(rng, 2, list(range(6)), 13), 1_002_000_000)
        assert pair.xt.reg_tp[ent] != NO_ROW, "the plan of a robot answered at the gate was dropped"
        assert pair.xt.reg_dropped_ns[ent] == 0
        pair.packet(statuses(rng, 2, list(range(6)), 20), 1_004_000_000)  # (six periods never sent)
        assert pair.xt.reg_tp[ent] == NO_ROW and pair.xt.reg_dropped_why[ent] == DROP_WATCHDOG
    finally:
        pair.close()
