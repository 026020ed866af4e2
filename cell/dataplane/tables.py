"""The data plane's match-action state (NSDI'22 Fig. 3-4): registers, TPStepper, TargetData,
TrajectorySwitcher.

An *entity* is what one set of registers drives: one robot, or several robots
merged into one (their joints side by side) so that they step together.

The packet path only gathers from numpy arrays by row: its cost does not grow
with the number of trajectory points (TPs) loaded.  Matching a (entity, TP
id) key to its row, and the TP a row links to, is the control plane's job:
it keeps the keys in dicts and resolves links when TPs are inserted, also
links to TPs that are loaded later (a streamed trajectory's next episode).
Every control-plane call checks the whole batch first and then applies all
of it, so the packet path sees a batch entirely or not at all.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Generator, Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike

from cell.bus import FaultCode
from cell.robot.datagram import SCALE

NO_ROW = -1
T = TypeVar("T", int, np.ndarray)
LIMIT_RAD = 1e6  # |target| bound (rad, rad/s): far beyond any arm, far inside int64 fixed point
SLICE = 512  # keys handled between two yields of a staged update (each slice a few hundred us at most)


_ID_MASK = 0xFFFF_FFFF


def tpkey(entity: T, tp_id: T) -> T:
    """The control plane's key of a TP: entity << 32 | TP id (ints or int64 arrays alike)."""
    return (entity << 32) | tp_id


class Refused(Exception):
    """A control-plane request that cannot be applied; nothing of it was applied."""

    def __init__(self, code: FaultCode, reason: str) -> None:
        self.code, self.reason = code, reason
        super().__init__(f"{code}: {reason}")


@dataclass(frozen=True)
class TP:
    """A trajectory point as the controller loads it (SI units; converted to fixed point here)."""

    robot: int  # a robot id; for a merged entity, any of its robots
    id: int
    next_id: int  # the TP that follows (itself for a hold, an earlier one for a loop)
    duration_s: float  # section duration: the time allotted to reach this TP
    positions: Sequence[float]  # one per joint of the entity (rad)
    velocities: Sequence[float]  # (rad/s)


@dataclass(frozen=True)
class TPBatch:
    """Many TPs as columns: the form updates travel and are applied in.

    A Python object (or protobuf message) per TP costs microseconds each, so
    1,600 of them would hold the packet path for milliseconds; columns are
    checked and written with a few numpy operations.
    """

    robot: np.ndarray  # (n,) int64
    id: np.ndarray  # (n,) int64
    next_id: np.ndarray  # (n,) int64
    duration_s: np.ndarray  # (n,) float64
    joints: np.ndarray  # (n,) how many values each TP has
    positions: np.ndarray  # (n, width) float64 rad; zero beyond a TP's joints
    velocities: np.ndarray  # (n, width) float64 rad/s

    def __len__(self) -> int:
        return int(self.robot.size)

    @classmethod
    def of(cls, tps: Sequence[TP]) -> TPBatch:
        joints = np.array([len(tp.positions) for tp in tps], np.int64)
        if any(len(tp.velocities) != len(tp.positions) for tp in tps):
            raise ValueError("a TP needs as many velocities as positions")
        flat_p = [x for tp in tps for x in tp.positions]
        flat_v = [x for tp in tps for x in tp.velocities]
        return cls.from_flat(
            [tp.robot for tp in tps],
            [tp.id for tp in tps],
            [tp.next_id for tp in tps],
            [tp.duration_s for tp in tps],
            joints,
            flat_p,
            flat_v,
        )

    @property
    def keys(self) -> np.ndarray:
        """(n, 2) robot, id: what removes these TPs again."""
        return np.stack([self.robot, self.id], axis=1)

    @classmethod
    def parked(cls, robots: ArrayLike, ids: ArrayLike, joints: int = 6) -> TPBatch:
        """TPs at zero that lead to themselves, for no register to point at: a benchmark's table
        load (a playback buffer's episodes not yet switched to, or left behind)."""
        ids = np.asarray(ids, np.int64)
        zeros = np.zeros(ids.size * joints)
        return cls.from_flat(robots, ids, ids, np.ones(ids.size), np.full(ids.size, joints), zeros, zeros)

    @classmethod
    def from_flat(
        cls,
        robot: ArrayLike,
        id: ArrayLike,
        next_id: ArrayLike,
        duration_s: ArrayLike,
        joints: ArrayLike,
        positions: ArrayLike,
        velocities: ArrayLike,
    ) -> TPBatch:
        """From columns, joint values flat TP after TP (the wire form); ValueError if they disagree."""
        cols = [np.asarray(c, np.int64).reshape(-1) for c in (robot, id, next_id, joints)]
        dur = np.asarray(duration_s, np.float64).reshape(-1)
        pos = np.asarray(positions, np.float64).reshape(-1)
        vel = np.asarray(velocities, np.float64).reshape(-1)
        n = cols[0].size
        if any(c.size != n for c in (*cols, dur)):
            raise ValueError(f"TP columns of different lengths ({[c.size for c in (*cols, dur)]})")
        j = cols[3]
        if j.size and (j.min() < 0 or j.max() > 64):
            raise ValueError("joints per TP must be 0..64")
        total = int(j.sum())
        if pos.size != total or vel.size != total:
            raise ValueError(f"{total} joint values expected: {pos.size} positions, {vel.size} velocities")
        width = int(j.max(initial=0))
        if n and (j == width).all():  # the usual batch: one entity shape
            p2, v2 = pos.reshape(n, width), vel.reshape(n, width)
        else:
            mask = np.arange(width) < j[:, None]
            p2, v2 = np.zeros((n, width)), np.zeros((n, width))
            p2[mask], v2[mask] = pos, vel
        return cls(cols[0], cols[1], cols[2], dur, j, p2, v2)

    def take(self, idx: ArrayLike) -> TPBatch:
        i = np.asarray(idx, np.int64)
        return TPBatch(
            self.robot[i],
            self.id[i],
            self.next_id[i],
            self.duration_s[i],
            self.joints[i],
            self.positions[i],
            self.velocities[i],
        )


class Tables:
    def __init__(self, capacity: int = 50_000, max_entities: int = 1024, max_joints: int = 12) -> None:
        self.capacity = capacity
        self.max_joints = max_joints
        self.max_entities = max_entities
        # robot -> entity and the robot's first joint within it (robot ids are u16)
        self.robot_entity = np.full(1 << 16, NO_ROW, np.int32)
        self.robot_joint0 = np.zeros(1 << 16, np.int32)
        self.entity_joints = np.zeros(max_entities, np.int32)
        self.entities = 0
        # registers, one per entity (Algorithm 1).  REG_nextTp is not stored: each step reads it from
        # the current TP's links (TrajectorySwitcher, then TPStepper; effective_next), because a stored
        # copy would go stale whenever a switch is set or a streamed link resolves later
        self.reg_tp = np.full(max_entities, NO_ROW, np.int32)
        self.reg_next_time = np.zeros(max_entities, np.int64)  # data-plane clock, ns
        # a step was due but the next TP is not loaded (the controller fell behind or died): the
        # entity holds its TP's position with target velocity 0, never coasting on past it
        self.reg_stalled = np.zeros(max_entities, bool)
        self.reg_stall_ns = np.zeros(max_entities, np.int64)  # when the stall began
        # when, and why (DROP_*), the entity's trajectory was last dropped (Pipeline.drop): its
        # robots then hold still with commands of 0 until the controller sets its registers again
        self.reg_dropped_ns = np.zeros(max_entities, np.int64)
        self.reg_dropped_why = np.zeros(max_entities, np.int8)
        # the last status of each robot's joints (wire fixed point) and when it came: registers the
        # controller reads to plan from where a robot is (re-planning, stops)
        self.status_pos = np.zeros((1 << 16, max_joints), np.int64)
        self.status_vel = np.zeros((1 << 16, max_joints), np.int64)
        self.status_ns = np.zeros(1 << 16, np.int64)
        self.status_seq = np.zeros(1 << 16, np.int64)  # its sequence number (the robot's own tick count)
        # TPStepper (+ TargetData), one row per TP
        self.valid = np.zeros(capacity, bool)
        self.next_row = np.full(capacity, NO_ROW, np.int32)
        self.duration = np.zeros(capacity, np.int64)  # ns
        self.trg_pos = np.zeros((capacity, max_joints), np.int64)
        self.trg_vel = np.zeros((capacity, max_joints), np.int64)
        # TrajectorySwitcher: the TP a row's successor is overridden with
        self.switch_row = np.full(capacity, NO_ROW, np.int32)
        # the control plane's indexes
        # the control plane's indexes.  A TP's key is one int, entity << 32 | TP id (tpkey()): ints
        # hash fast and, unlike tuples, are no work for the garbage collector, whose passes over
        # 50,000 keys would otherwise stall the packet path for milliseconds
        self._row: dict[int, int] = {}  # key -> row
        self._key = np.full(capacity, -1, np.int64)  # row -> key
        self._next_id = np.zeros(capacity, np.int64)
        self._switch_id: dict[int, int] = {}  # row -> the TP id it switches to
        self._waiting: dict[int, set[tuple[int, str]]] = defaultdict(set)  # key -> links waiting for it
        self._free = list(range(capacity - 1, -1, -1))
        self._entity: dict[int, int] = {}  # robot -> entity, for the control plane (numpy scalars are slow)

    # --- robots and entities -----------------------------------------------------------------

    def add_robot(self, robot: int, joints: int = 6) -> int:
        """Give a robot its own entity (idempotent); return the entity."""
        if self.robot_entity[robot] != NO_ROW:
            return int(self.robot_entity[robot])
        return self._new_entity([robot], [joints])

    def merge(self, robots: Sequence[int], joints: int = 6) -> int:
        """One entity for several robots, joints side by side in the order given; return it."""
        if len(set(robots)) != len(robots) or len(robots) < 2:
            raise Refused(FaultCode.BAD_REQUEST, "merge needs two or more distinct robots")
        for r in robots:
            e = self.robot_entity[r]
            if e != NO_ROW and self.reg_tp[e] != NO_ROW:
                why = f"robot {r} is following a trajectory; stop it before merging"
                raise Refused(FaultCode.IN_USE, why)
        return self._new_entity(list(robots), [joints] * len(robots))

    def _new_entity(self, robots: list[int], joints: list[int]) -> int:
        total = sum(joints)
        if total > self.max_joints:
            raise Refused(FaultCode.TOO_MANY_JOINTS, f"{total} joints, at most {self.max_joints} per entity")
        if self.entities >= self.max_entities:
            raise Refused(FaultCode.TABLE_FULL, f"all {self.max_entities} entities in use")
        e = self.entities
        self.entities += 1
        offset = 0
        for r, j in zip(robots, joints, strict=True):
            self.robot_entity[r] = e
            self._entity[r] = e
            self.robot_joint0[r] = offset
            offset += j
        self.entity_joints[e] = total
        return e

    def entity_of(self, robot: int) -> int:
        e = self._entity.get(robot)
        if e is None:
            raise Refused(FaultCode.UNKNOWN_ROBOT, f"robot {robot} is not known to the data plane")
        return e

    def entities_of(self, robots: np.ndarray) -> np.ndarray:
        """entity_of for an array of robot ids, at once."""
        robots = np.asarray(robots, np.int64)
        inside = (robots >= 0) & (robots < self.robot_entity.size)
        ents = np.where(inside, self.robot_entity[np.where(inside, robots, 0)], NO_ROW)
        unknown = np.flatnonzero(ents == NO_ROW)
        if unknown.size:
            why = f"robot {int(robots[unknown[0]])} is not known to the data plane"
            raise Refused(FaultCode.UNKNOWN_ROBOT, why)
        return ents.astype(np.int64)

    # --- TPStepper / TargetData ----------------------------------------------------------------

    @property
    def loaded(self) -> int:
        """TPs the packet path sees: not the rows a staged update holds but has not flipped in yet,
        nor those it has taken out but not yet given back to the free list."""
        return int(np.count_nonzero(self.valid))

    def insert(self, tps: Sequence[TP] | TPBatch) -> None:
        """Insert or replace TPs, atomically; Refused (table_full, unknown_robot, ...) before any change."""
        self.update(insert=tps)

    def _replace(self, rows: list[int], batch: TPBatch) -> None:
        """New contents for TPs already loaded (in the flip: in place, the rows stay where they are)."""
        self._write_rows(np.array(rows, np.int64), batch)
        for row, nxt in zip(rows, batch.next_id.tolist(), strict=True):
            e = self._key_entity(row)
            self._unwait(tpkey(e, int(self._next_id[row])), (row, "next"))
            self._next_id[row] = nxt
            self._link(row, "next", tpkey(e, nxt))

    def _write_rows(self, rows: np.ndarray, batch: TPBatch) -> None:
        """TargetData and section durations of the given rows."""
        w = batch.positions.shape[1]
        self.trg_pos[rows, :w] = np.rint(batch.positions * SCALE).astype(np.int64)
        self.trg_vel[rows, :w] = np.rint(batch.velocities * SCALE).astype(np.int64)
        self.trg_pos[rows, w:] = 0
        self.trg_vel[rows, w:] = 0
        self.duration[rows] = np.rint(batch.duration_s * 1e9).astype(np.int64)

    def _link(self, row: int, kind: str, target: int) -> None:
        to = self._row.get(target, NO_ROW)
        (self.next_row if kind == "next" else self.switch_row)[row] = to
        if to == NO_ROW:
            self._waiting[target].add((row, kind))

    def delete(self, keys: Iterable[tuple[int, int]]) -> int:
        """Delete TPs given as (robot, TP id), atomically; unknown ones are ignored; return how many went.

        A TP that a robot is heading to, or will step to next, is refused (in_use): switch
        or stop the robot first.
        """
        return self.update(remove=list(keys))

    def _forget_waits(self, row: int) -> None:
        e = self._key_entity(row)
        self._unwait(tpkey(e, int(self._next_id[row])), (row, "next"))
        if row in self._switch_id:
            self._unwait(tpkey(e, self._switch_id[row]), (row, "switch"))

    def _unwait(self, target: int, waiter: tuple[int, str]) -> None:
        waiters = self._waiting.get(target)
        if waiters is not None:
            waiters.discard(waiter)
            if not waiters:  # no empty sets left behind: streaming would grow them forever
                del self._waiting[target]

    def _key_entity(self, row: int) -> int:
        return int(self._key[row]) >> 32

    def effective_next(self, rows: np.ndarray) -> np.ndarray:
        """The row each row steps to: its TrajectorySwitcher entry, else its TPStepper link (NO_ROW: none)."""
        safe = np.maximum(rows, 0)
        nxt = np.where(self.switch_row[safe] != NO_ROW, self.switch_row[safe], self.next_row[safe])
        return np.where(rows == NO_ROW, NO_ROW, nxt)

    def row_of(self, robot: int, tp_id: int) -> int:
        row = self._row.get(tpkey(self.entity_of(robot), tp_id))
        if row is None:
            raise Refused(FaultCode.UNKNOWN_TP, f"robot {robot} has no TP {tp_id} loaded")
        return row

    # --- TrajectorySwitcher ----------------------------------------------------------------------

    def set_switch(self, robot: int, tp_id: int, next_id: int) -> None:
        """After TP tp_id, go to next_id instead of its successor (it may be loaded later)."""
        row = self.row_of(robot, tp_id)
        e = self.entity_of(robot)
        self.unset_switch(robot, tp_id)
        self._switch_id[row] = next_id
        self._link(row, "switch", tpkey(e, next_id))

    def unset_switch(self, robot: int, tp_id: int) -> None:
        row = self.row_of(robot, tp_id)
        old = self._switch_id.pop(row, None)
        if old is not None:
            self._unwait(tpkey(self.entity_of(robot), old), (row, "switch"))
        self.switch_row[row] = NO_ROW

    # --- registers ------------------------------------------------------------------------------

    def set_registers(self, robot: int, tp_id: int, next_time_ns: int) -> None:
        """Make the robot's entity head for TP tp_id and step on at next_time_ns (absolute)."""
        e = self.entity_of(robot)
        row = self.row_of(robot, tp_id)
        self.reg_tp[e] = row
        self.reg_next_time[e] = next_time_ns
        self.reg_stalled[e] = False

    def clear_registers(self, robot: int) -> None:
        """The entity follows nothing: its robots are told to hold (velocity 0)."""
        e = self.entity_of(robot)
        self.reg_tp[e] = NO_ROW
        self.reg_stalled[e] = False

    def keys_of(self, robot: int) -> list[tuple[int, int]]:
        """Every loaded TP of the robot's entity, as (robot, TP id) keys (a scan: for flushes, not hot)."""
        e = self.entity_of(robot)
        return [(robot, key & _ID_MASK) for key in self._row if key >> 32 == e]

    def current_tp(self, robot: int) -> int | None:
        row = int(self.reg_tp[self.entity_of(robot)])
        return None if row == NO_ROW else int(self._key[row]) & _ID_MASK

    # --- one atomic update ------------------------------------------------------------------------

    def update(
        self,
        insert: Sequence[TP] | TPBatch = (),
        remove: Sequence[tuple[int, int]] | np.ndarray = (),
        switches: Sequence[tuple[int, int, int | None]] = (),
        registers: Sequence[tuple[int, int | None, int]] = (),
    ) -> int:
        """Apply a whole control-plane batch or none of it, in one go; return how many TPs were removed."""
        steps = self.staged_update(insert, remove, switches, registers)
        while True:
            try:
                next(steps)
            except StopIteration as done:
                return int(done.value)

    def staged_update(
        self,
        insert: Sequence[TP] | TPBatch = (),
        remove: Sequence[tuple[int, int]] | np.ndarray = (),
        switches: Sequence[tuple[int, int, int | None]] = (),
        registers: Sequence[tuple[int, int | None, int]] = (),
        slice_size: int = SLICE,
    ) -> Generator[None, None, int]:
        """update() in slices: it yields between them, and the packet path may run at every yield.

        The packet path only reads the arrays, so the batch stays atomic for it:
        checks read; new TPs go into fresh rows that nothing links to yet; one
        flip then makes everything visible at once (links into the new TPs,
        replaced TPs, switches, registers, deleted TPs gone); the deleted rows'
        bookkeeping is cleaned up afterwards.  The in-use check for deletions is
        made in the flip, against where the robots are then.  One update at a time.

        remove: (robot, TP id) pairs, or an (n, 2) array of them; switches: (robot, branching TP,
        next TP or None to unset); registers: (robot, TP or None to clear, next_time_ns).
        Returns how many TPs were removed.
        """
        # --- 1. checks (nothing they rely on changes meanwhile: robots only move) ---------------
        batch = insert if isinstance(insert, TPBatch) else TPBatch.of(list(insert))
        karr = self._check(batch)
        keys = karr.tolist()
        yield
        if np.unique(karr).size != karr.size:
            raise Refused(FaultCode.BAD_REQUEST, "a TP appears twice in one batch")
        loaded = np.fromiter([k in self._row for k in keys], bool, len(keys))
        fresh, replaced = np.flatnonzero(~loaded), np.flatnonzero(loaded)
        if len(fresh) > len(self._free):
            free = len(self._free)
            why = f"{len(fresh)} new TPs, {free} of {self.capacity} places free (delete some first)"
            raise Refused(FaultCode.TABLE_FULL, why)
        new_keys = set(keys)

        def exists(robot: int, tp_id: int) -> bool:
            key = tpkey(self.entity_of(robot), tp_id)
            return key in self._row or key in new_keys

        tp_id: int | None  # (a switch's TP; a register's, None to clear)
        for robot, tp_id, _ in switches:
            if not exists(robot, tp_id):
                raise Refused(FaultCode.UNKNOWN_TP, f"switch at TP {tp_id} of robot {robot}: no such TP")
        moved: dict[int, int | None] = {}
        for robot, tp_id, _ in registers:
            if tp_id is not None and not exists(robot, tp_id):
                raise Refused(FaultCode.UNKNOWN_TP, f"registers of robot {robot}: no TP {tp_id}")
            moved[self.entity_of(robot)] = tp_id
        yield
        pairs = np.asarray(remove, np.int64).reshape(-1, 2)
        named = (tpkey(self.entities_of(pairs[:, 0]), pairs[:, 1])).tolist()
        is_gone = np.zeros(self.capacity, bool)  # the rows to delete (unknown TPs: none; twice: once)
        for i in range(0, len(named), slice_size * 2):
            found = np.array([self._row.get(k, NO_ROW) for k in named[i : i + slice_size * 2]], np.int64)
            is_gone[found[found != NO_ROW]] = True
            yield
        gone = np.flatnonzero(is_gone)
        for e, tp_id in moved.items():
            row = None if tp_id is None else self._row.get(tpkey(e, tp_id))  # None too: inserted now
            if row is not None and is_gone[row]:
                raise Refused(FaultCode.IN_USE, f"TP {tp_id} is both started and deleted")

        # --- 2. stage new TPs in fresh rows nothing links to yet (invisible to the packet path) ---
        staged: dict[int, int] = {}  # also entered in the index at once, taken out if refused
        staged_rows = np.empty(fresh.size, np.int64)  # the row of each fresh TP
        waits: list[tuple[int, int]] = []
        flipping = False
        targets = tpkey(karr >> 32, batch.next_id)  # the keys they link to
        try:
            for i in range(0, fresh.size, slice_size):
                idx = fresh[i : i + slice_size]
                taken = self._free[len(self._free) - idx.size :]
                del self._free[len(self._free) - idx.size :]
                staged.update(zip(karr[idx].tolist(), taken, strict=True))
                self._row.update(zip(karr[idx].tolist(), taken, strict=True))
                rows = staged_rows[i : i + idx.size]
                rows[:] = taken
                self._key[rows] = karr[idx]
                self._next_id[rows] = batch.next_id[idx]
                self._write_rows(rows, batch.take(idx))
                yield
            for i in range(0, fresh.size, slice_size):
                rows = staged_rows[i : i + slice_size]
                wanted = targets[fresh[i : i + slice_size]].tolist()
                to = [self._row.get(t, NO_ROW) for t in wanted]
                to = [NO_ROW if x != NO_ROW and is_gone[x] else x for x in to]
                self.next_row[rows] = to
                self.switch_row[rows] = NO_ROW
                waits += [(t, r) for t, r, x in zip(wanted, rows.tolist(), to, strict=True) if x == NO_ROW]
                yield
            # the valid rows linking to TPs about to go (the flip adds those it links itself)
            both, none = (self.next_row, self.switch_row), np.zeros(0, np.int64)
            pointing = [self._links_into(arr, is_gone) if gone.size else none for arr in both]
            yield
            # --- 3. the flip: everything visible in one step ------------------------------------
            self.flip_begin()
            flipping = True
            if gone.size:
                current = self.reg_tp[: self.entities].astype(np.int64)
                upcoming = self.effective_next(current)
                stays = np.ones(self.entities, bool)
                stays[list(moved)] = False
                hit = stays & (
                    ((current != NO_ROW) & is_gone[np.maximum(current, 0)])
                    | ((upcoming != NO_ROW) & is_gone[np.maximum(upcoming, 0)])
                )
                if hit.any():
                    e = int(np.flatnonzero(hit)[0])
                    why = f"a TP entity {e} is following is to be deleted; switch or stop it first"
                    raise Refused(FaultCode.IN_USE, why)
        except BaseException:
            if flipping:
                self.flip_end()
            for key in staged:  # never visible: forget them and give the rows back
                del self._row[key]
            self._free.extend(staged.values())
            raise
        try:
            for target, row in waits:
                self._waiting[target].add((row, "next"))
            for key in staged.keys() & self._waiting.keys():  # the few links that waited for these TPs
                for waiter, kind in self._waiting.pop(key):
                    (self.next_row if kind == "next" else self.switch_row)[waiter] = staged[key]
            self.valid[staged_rows] = True
            touched = [self._row[keys[i]] for i in replaced.tolist()]  # rows whose links change in the flip
            if touched:  # in place: rare, and small
                self._replace(touched, batch.take(replaced))
            for robot, tp_id, nxt in switches:
                if nxt is None:
                    self.unset_switch(robot, tp_id)
                else:
                    self.set_switch(robot, tp_id, nxt)
                touched.append(self.row_of(robot, tp_id))
            for robot, tp_id, next_time in registers:
                if tp_id is None:
                    self.clear_registers(robot)
                else:
                    self.set_registers(robot, tp_id, next_time)
            if gone.size:
                self.valid[gone] = False
                links = zip((self.next_row, self.switch_row), ("next", "switch"), pointing, strict=True)
                for arr, kind, rows in links:
                    for w in self._links_into(arr, is_gone, np.union1d(rows, touched)).tolist():
                        target = int(self._key[arr[w]])
                        arr[w] = NO_ROW
                        self._waiting[target].add((w, kind))
        finally:
            self.flip_end()
        if not gone.size:
            return 0
        yield
        # --- 4. the deleted rows' bookkeeping, in slices ---------------------------------------
        waiting = set(gone[self.next_row[gone] == NO_ROW].tolist())  # few: rows sitting in a wait list,
        waiting |= {r for r in self._switch_id if is_gone[r]}  # or with a switch
        for row in waiting:
            self._forget_waits(row)  # both its link's and its switch's waits
            self._switch_id.pop(row, None)
        yield
        gone_keys = self._key[gone].tolist()
        for i in range(0, len(gone_keys), slice_size * 2):
            for key in gone_keys[i : i + slice_size * 2]:
                del self._row[key]
            yield
        self.next_row[gone] = NO_ROW
        self.switch_row[gone] = NO_ROW
        self._free.extend(gone.tolist())
        return int(gone.size)

    def flip_begin(self) -> None:
        """A flip starts: a packet path running beside us (the XDP backend) must not read the tables
        until flip_end().  Here, the packet path runs between our steps: nothing to do."""

    def flip_end(self) -> None:
        """The flip is done (or abandoned): the packet path may read the tables again."""

    def _links_into(self, arr: np.ndarray, is_gone: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """The valid rows (of `rows`; default all) whose link in `arr` points at a row marked in is_gone.
        Only the valid rows' links are read: in the XDP program's maps a link is a field of a row's
        record, and a stride over all 50,000 records was a quarter of a fleet's control plane."""
        if rows is None:
            rows = np.flatnonzero(self.valid)
        else:
            rows = rows.astype(np.int64)
            rows = rows[self.valid[rows]]
        to = arr[rows]
        return rows[(to != NO_ROW) & is_gone[np.maximum(to, 0)]]

    def _check(self, batch: TPBatch) -> np.ndarray:
        """Refused unless every TP fits its entity; their keys (tpkey)."""
        if not len(batch):
            return np.zeros(0, np.int64)
        ents = self.entities_of(batch.robot)
        want = self.entity_joints[ents]

        def first(bad: np.ndarray) -> str:
            i = int(np.flatnonzero(bad)[0])
            return f"TP {int(batch.id[i])} of robot {int(batch.robot[i])}"

        if (bad := batch.joints != want).any():
            n = int(want[np.flatnonzero(bad)[0]])
            raise Refused(FaultCode.BAD_REQUEST, f"{first(bad)}: {n} joint values expected")
        if (bad := ~(batch.duration_s > 0) | ~np.isfinite(batch.duration_s)).any():
            raise Refused(FaultCode.BAD_REQUEST, f"{first(bad)}: section duration must be > 0")
        ids = np.concatenate([batch.id, batch.next_id])
        if ((ids < 0) | (ids >= 2**32)).any():
            raise Refused(FaultCode.BAD_REQUEST, "TP ids are u32")
        values = np.concatenate([batch.positions, batch.velocities], axis=1)
        if (bad := ~(np.abs(values) < LIMIT_RAD).all(axis=1)).any():
            raise Refused(FaultCode.BAD_REQUEST, f"{first(bad)}: a joint value is not finite or out of range")
        return tpkey(ents, batch.id)
