"""The data plane's two pipelines (NSDI'22, Algorithms 1 and 2), run over a batch of status datagrams.

Ingress steps each entity along its trajectory: when the data-plane clock
reaches REG_nextTime, the entity moves to the next TP (TrajectorySwitcher
first, then TPStepper) and REG_nextTime grows by the new section's duration
(additive deadlines keep robots started together together).  One step per
packet: an entity with k packets in the batch steps at most k times; every
step after the first packet's is a resubmission in the P4 design, counted.

Egress turns each status into a command with the P-controller
    v_new = v_curr + c1 (v_trg - v_curr) + c2 (p_trg - p_curr)
computed as the switch does: TargetData gives (v_trg, p_trg), three
Transform tables give (1 - c1) v_curr, c1 v_trg and (c2 - 1) p_diff (the
"(c-1)x" trick, p_diff added back exactly), and LimitVelocity clamps the sum.
Integer arithmetic only, on the wire's fixed-point values; time is
CLOCK_MONOTONIC in ns.

A trajectory is dropped (registers cleared, its robots told 0: they stand) when
resuming it would make a robot lunge after a plan that went on without it: a
robot whose status numbers jumped past its watchdog (it lived on without our
commands and has protective-stopped), a robot not heard for QUIET_NS (it, or
we, hung), or an underrun (the next TP missing) that lasts longer than
STALL_DROP_NS (the controller is gone or far behind).
A short underrun holds the last TP's position and goes on when the TP comes.

A stop (from the Responsive Link's event socket, not the controller) sets a
robot's REG_stop: from then on its commands are the StopRamp, each one its
status velocity brought StopRamp[joint] closer to 0 (the deceleration over one
command window), then 0, whatever its trajectory says, until it is cleared.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cell.dataplane.approx import LimitVelocity, TransformTable, table_index
from cell.dataplane.tables import NO_ROW, Tables
from cell.robot.datagram import SCALE, Kind

# inputs from the wire are clamped to this magnitude (about 1e11 rad) so no sum can overflow int64
INPUT_LIMIT = 1 << 60
TERM_LIMIT = 1 << 60
QUIET_NS = 500_000_000  # no status from a robot this long: it, or we, hung; its plan is stale
STALL_DROP_NS = 50_000_000  # an underrun this long ends the trajectory (catching up would be a lunge)
# why a trajectory was dropped (Tables.reg_dropped_why)
DROP_WATCHDOG, DROP_UNDERRUN, DROP_STOP, DROP_QUIET = 1, 2, 3, 4


class TransformBank:
    """One TransformTable per joint, stacked so a batch mixing joints is one gather."""

    def __init__(self, factors: Sequence[float], n_bits: int) -> None:
        self.n = n_bits
        self.tables = [TransformTable(c, n_bits) for c in factors]
        self.stack = np.stack([t.table for t in self.tables])  # (joint, sign, entry)
        np.clip(self.stack, -TERM_LIMIT, TERM_LIMIT, out=self.stack)

    def __call__(self, x: np.ndarray, joint: np.ndarray) -> np.ndarray:
        return self.lookup(table_index(x, self.n), joint)

    def lookup(self, index: np.ndarray, joint: np.ndarray) -> np.ndarray:
        """The entries at table_index() positions: matching once serves banks of the same n."""
        return self.stack.reshape(self.stack.shape[0], -1)[joint, index]

    @property
    def entries(self) -> int:
        return self.stack.size


@dataclass(frozen=True)
class ControlConstants:
    """The P-controller of each joint: v_new = v + c1 (v_trg - v) + c2 (p_trg - p); n significant bits."""

    c1: tuple[float, ...]
    c2: tuple[float, ...]
    n_bits: int
    v_max: tuple[float, ...]  # rad/s, the joints' limits


@dataclass
class PipelineCounters:
    packets: int = 0
    holds: int = 0  # status of a robot with no trajectory (or not known): answered with 0
    steps: int = 0  # TP steps taken
    resubmits: int = 0  # steps beyond the first of an entity in one batch (resubmitted packets on a switch)
    stalls: int = 0  # a step was due but the next TP is not loaded (a streaming underrun)
    limited: int = 0  # commands clamped by LimitVelocity
    stop_commands: int = 0  # commands from the StopRamp (robots under REG_stop)
    dropped: int = 0  # trajectories dropped (Tables.reg_dropped_why says why)
    dropped_stop: int = 0  # of them, by a stop order (an e-stop, a stop): asked for, not a fault


class Pipeline:
    def __init__(self, tables: Tables, constants: ControlConstants) -> None:
        self.t = tables
        self.counters = PipelineCounters()
        self.reg_stop = np.zeros(1 << 16, bool)  # per robot: commands come from the StopRamp
        self.stopping = 0  # robots with REG_stop set (0: the packet path skips the stop stage)
        self.stop_ramp = np.zeros(len(constants.c1), np.int64)  # per joint, wire units per window
        # per robot, when resuming its plan would be a lunge (0: never judged): a jump in its status
        # sequence numbers beyond stale_periods means it lived that many periods without hearing us
        # (a robot ticks, and numbers its statuses, on its own clock: its watchdog has stopped it);
        # no status at all for quiet_ns means it, or we, hung that long.  A time gap alone is not
        # enough: a robot process held up by the OS for 40 ms resumes with the next number, its
        # watchdog never fired, and its plan goes on
        self.stale_periods = np.zeros(1 << 16, np.int64)
        self.quiet_ns = np.zeros(1 << 16, np.int64)
        self.install(self.build(constants))

    @staticmethod
    def build(constants: ControlConstants) -> tuple:
        """Generate every table for a set of constants (slow-ish: keep it off the packet path)."""
        j = len(constants.c1)
        if not (len(constants.c2) == len(constants.v_max) == j):
            raise ValueError("c1, c2 and v_max need one value per joint")
        if not 2 <= constants.n_bits <= 16:
            raise ValueError(f"n_bits must be 2..16 (got {constants.n_bits})")
        if not all(0 < v <= 10 for v in constants.v_max):
            raise ValueError("v_max must be in (0, 10] rad/s for every joint")
        return (
            constants,
            TransformBank([1.0 - c for c in constants.c1], constants.n_bits),
            TransformBank(list(constants.c1), constants.n_bits),
            TransformBank([c - 1.0 for c in constants.c2], constants.n_bits),
            LimitVelocity(np.rint(np.array(constants.v_max) * SCALE).astype(np.int64)),
        )

    def install(self, built: tuple) -> None:
        """Swap in tables made by build(): one step, between two packet batches."""
        (
            self.constants,
            self.transform_curr_velocity,
            self.transform_trg_velocity,
            self.transform_diff_position,
            self.limit_velocity,
        ) = built
        self.joints = len(self.constants.c1)

    # --- Algorithm 1 -------------------------------------------------------------------------

    def ingress(self, entities: np.ndarray, packets: np.ndarray, now: int | np.ndarray) -> None:
        """Step the given entities (each with its packet count in this batch) along their trajectories;
        `now`: when their packets came in (ns; one time for all, or one per entity)."""
        t, c = self.t, self.counters
        budget = packets.copy()
        at = np.broadcast_to(np.asarray(now, np.int64), entities.shape)
        first = True
        while entities.size:
            cur = t.reg_tp[entities]
            due = (cur != NO_ROW) & (at >= t.reg_next_time[entities])
            if not due.any():
                return
            e, cur, at = entities[due], cur[due], at[due]
            nxt = t.effective_next(cur)
            ok = nxt != NO_ROW
            if not ok.all():
                c.stalls += int((~ok).sum())
                stuck, at_stuck = e[~ok], at[~ok]
                fresh = ~t.reg_stalled[stuck]
                t.reg_stalled[stuck[fresh]] = True
                t.reg_stall_ns[stuck[fresh]] = at_stuck[fresh]
                self.drop(
                    stuck[at_stuck - t.reg_stall_ns[stuck] > STALL_DROP_NS],
                    int(at_stuck.max()),
                    DROP_UNDERRUN,
                )
            e, nxt, at = e[ok], nxt[ok], at[ok]
            t.reg_stalled[e] = False
            t.reg_tp[e] = nxt
            t.reg_next_time[e] += t.duration[nxt]
            c.steps += e.size
            if not first:
                c.resubmits += e.size
            first = False
            left = budget[due][ok] - 1
            more = left > 0
            entities, budget, at = e[more], left[more], at[more]

    # --- the whole packet path ---------------------------------------------------------------

    def process(
        self, recs: np.ndarray, now: int, stops: bool = True, arrival: np.ndarray | None = None
    ) -> None:
        """Turn valid status records (datagram.DTYPE) into commands, in place; `now` in ns.  stops=False
        leaves the stop stage to the caller (a batch run in slices takes it once, over all of it).

        arrival: when each record came in (ns, the kernel's receive timestamp), as a switch's
        ingress timestamp: TPs step by it, so a batch that waited for the CPU still steps on the
        status period its packets belong to (stepping by `now` shifted whole sections by a
        period whenever the packet path ran more than 1.5 ms behind)."""
        t, c = self.t, self.counters
        n = recs.size
        if n == 0:
            return
        c.packets += n
        rid = recs["robot_id"].astype(np.int64)
        jid = recs["joint_id"].astype(np.int64)
        ent = t.robot_entity[rid].astype(np.int64)
        known = ent != NO_ROW
        seq = recs["seq"].astype(np.int64)
        jump = (seq - t.status_seq[rid]) & 0xFFFFFFFF
        last, quiet = t.status_ns[rid], self.quiet_ns[rid]
        judged = known & (last > 0) & (quiet > 0)  # configured robots heard of before
        jumped = judged & (jump > self.stale_periods[rid])
        if jumped.any():
            self.drop(ent[jumped], now, DROP_WATCHDOG)
        silent = judged & (now - last > quiet) & ~jumped
        if silent.any():
            self.drop(ent[silent], now, DROP_QUIET)
        if known.any():
            counts = np.bincount(ent[known], minlength=t.entities)  # (faster than np.unique here)
            entities = np.flatnonzero(counts)
            if arrival is None:
                self.ingress(entities, counts[entities], now)
            else:
                at = np.empty(t.entities, np.int64)
                at[ent[known]] = arrival[known]  # (records in arrival order: an entity's latest wins)
                self.ingress(entities, counts[entities], at[entities])
        # Algorithm 2
        ent0 = np.maximum(ent, 0)
        row = np.where(known, t.reg_tp[ent0], NO_ROW)
        has = row != NO_ROW
        r = np.maximum(row, 0)
        j = np.where(has, t.robot_joint0[rid] + jid, 0)
        v_trg = t.trg_vel[r, j]  # TargetData
        v_trg[t.reg_stalled[ent0]] = 0  # stalled: hold the TP's position, no coasting
        p_trg = t.trg_pos[r, j]
        v = _clamp(recs["velocity"].astype(np.int64), INPUT_LIMIT)
        p = _clamp(recs["position"].astype(np.int64), INPUT_LIMIT)
        mine = jid < t.max_joints
        t.status_pos[rid[mine], jid[mine]] = p[mine]
        t.status_vel[rid[mine], jid[mine]] = v[mine]
        t.status_ns[rid] = now
        t.status_seq[rid] = seq
        diff = _clamp(p_trg - p, TERM_LIMIT)
        local = np.minimum(jid, self.joints - 1)
        # the three Transform tables share their key: match all three inputs in one pass
        idx = table_index(np.concatenate([v, v_trg, diff]), self.constants.n_bits)
        v_new = (
            self.transform_curr_velocity.lookup(idx[:n], local)
            + self.transform_trg_velocity.lookup(idx[n : 2 * n], local)
            + self.transform_diff_position.lookup(idx[2 * n :], local)
            + diff
        )
        out = self.limit_velocity(v_new, local)
        c.limited += int(((out != v_new) & has).sum())
        out[~has] = 0
        c.holds += int((~has).sum())
        recs["velocity"] = out
        recs["kind"] = Kind.COMMAND
        if stops and self.stopping:
            self.apply_stops(recs)

    def sweep(self, robots: np.ndarray, now: int) -> None:
        """Drop the trajectories of these robots that have gone quiet past their watchdog (the P4
        design would send itself a packet on a timer for this: no status, no packet to act on)."""
        last, quiet = self.t.status_ns[robots], self.quiet_ns[robots]
        gone = (last > 0) & (quiet > 0) & (now - last > quiet)  # (process()'s rule, without a packet)
        if gone.any():
            ent = self.t.robot_entity[robots[gone]].astype(np.int64)
            self.drop(ent[ent != NO_ROW], now, DROP_QUIET)

    def drop(self, entities: np.ndarray, now: int, why: int) -> None:
        """Clear the registers of these entities (see the module's docstring), noting when and why."""
        t = self.t
        e = np.unique(entities)
        e = e[t.reg_tp[e] != NO_ROW]
        if e.size:
            t.reg_tp[e] = NO_ROW
            t.reg_stalled[e] = False
            t.reg_dropped_ns[e] = now
            t.reg_dropped_why[e] = why
            self.counters.dropped += int(e.size)
            if why == DROP_STOP:
                self.counters.dropped_stop += int(e.size)

    # --- stops -------------------------------------------------------------------------------

    def set_stop_ramp(self, decel: Sequence[float] | np.ndarray, window_s: float) -> None:
        """StopRamp: per joint, the velocity a window's braking at `decel` (rad/s^2) takes away."""
        self.stop_ramp = np.rint(np.resize(np.asarray(decel, np.float64), self.joints) * window_s * SCALE)
        self.stop_ramp = self.stop_ramp.astype(np.int64)

    def apply_stops(self, cmds: np.ndarray) -> int:
        """Commands (processed records) of robots under REG_stop replaced by their StopRamp, from each
        joint's last status; the packet path runs it again over a whole batch before sending, so a
        stop set while the batch was being processed in slices holds for all of it."""
        rid = cmds["robot_id"].astype(np.int64)
        stop = self.reg_stop[rid]
        if not stop.any():
            return 0
        rid, jid = rid[stop], cmds["joint_id"][stop].astype(np.int64)
        jid = np.minimum(jid, self.t.max_joints - 1)
        cmds["velocity"][stop] = self.ramp(self.t.status_vel[rid, jid], jid)
        n = int(stop.sum())
        self.counters.stop_commands += n
        return n

    def ramp(self, v: np.ndarray, joint: np.ndarray) -> np.ndarray:
        """Stop commands: each velocity StopRamp[joint] closer to 0, never past it."""
        dv = self.stop_ramp[np.minimum(joint, self.joints - 1)]
        return np.sign(v) * np.maximum(np.abs(v) - dv, 0)

    def stop(self, robots: Sequence[int], on: bool = True) -> None:
        """Set (or clear) REG_stop of these robots."""
        self.reg_stop[np.asarray(robots, np.int64)] = on
        self.stopping = int(np.count_nonzero(self.reg_stop))


def _clamp(x: np.ndarray, limit: int) -> np.ndarray:
    """x within [-limit, limit], in place (two ufuncs: np.clip's wrapper costs more than the work)."""
    np.minimum(x, limit, out=x)
    return np.maximum(x, -limit, out=x)


def reference_command(
    v: float, p: float, v_trg: float, p_trg: float, c1: float, c2: float, v_max: float
) -> float:
    """The same controller in floating point, for checking the integer pipeline."""
    out = v + c1 * (v_trg - v) + c2 * (p_trg - p)
    return max(-v_max, min(v_max, out))
