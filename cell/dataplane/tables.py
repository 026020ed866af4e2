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

import numpy as np

from cell.robot.datagram import SCALE

NO_ROW = -1
SLICE = 256  # TPs handled between two yields of a staged update (each slice well under 1 ms)


class Refused(Exception):
    """A control-plane request that cannot be applied; nothing of it was applied."""

    def __init__(self, code: str, reason: str) -> None:
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
        # TPStepper (+ TargetData), one row per TP
        self.valid = np.zeros(capacity, bool)
        self.next_row = np.full(capacity, NO_ROW, np.int32)
        self.duration = np.zeros(capacity, np.int64)  # ns
        self.trg_pos = np.zeros((capacity, max_joints), np.int64)
        self.trg_vel = np.zeros((capacity, max_joints), np.int64)
        # TrajectorySwitcher: the TP a row's successor is overridden with
        self.switch_row = np.full(capacity, NO_ROW, np.int32)
        # the control plane's indexes
        self._row: dict[tuple[int, int], int] = {}
        self._key = [(-1, -1)] * capacity
        self._next_id = np.zeros(capacity, np.int64)
        self._switch_id: dict[int, int] = {}  # row -> the TP id it switches to
        self._waiting: dict[tuple[int, int], set[tuple[int, str]]] = defaultdict(set)
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
            raise Refused("bad_request", "merge needs two or more distinct robots")
        for r in robots:
            e = self.robot_entity[r]
            if e != NO_ROW and self.reg_tp[e] != NO_ROW:
                raise Refused("in_use", f"robot {r} is following a trajectory; stop it before merging")
        return self._new_entity(list(robots), [joints] * len(robots))

    def _new_entity(self, robots: list[int], joints: list[int]) -> int:
        total = sum(joints)
        if total > self.max_joints:
            raise Refused("too_many_joints", f"{total} joints, at most {self.max_joints} per entity")
        if self.entities >= self.max_entities:
            raise Refused("table_full", f"all {self.max_entities} entities in use")
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
            raise Refused("unknown_robot", f"robot {robot} is not known to the data plane")
        return e

    # --- TPStepper / TargetData ----------------------------------------------------------------

    @property
    def loaded(self) -> int:
        return self.capacity - len(self._free)

    def insert(self, tps: Sequence[TP]) -> None:
        """Insert or replace TPs, atomically; Refused (table_full, unknown_robot, ...) before any change."""
        self.update(insert=tps)

    def _insert_checked(self, tps: Sequence[TP]) -> None:
        keys = [(self.entity_of(tp.robot), tp.id) for tp in tps]
        rows = np.array([self._row[k] if k in self._row else self._alloc(k) for k in keys], np.int64)
        if rows.size == 0:
            return
        self._write_rows(rows, tps)
        for row, (e, _), tp in zip(rows.tolist(), keys, tps, strict=True):
            self._next_id[row] = tp.next_id
            self._link(row, "next", (e, tp.next_id))
        for row, key in zip(rows.tolist(), keys, strict=True):
            for waiter, kind in self._waiting.pop(key, ()):
                (self.next_row if kind == "next" else self.switch_row)[waiter] = row
        self.valid[rows] = True

    def _write_rows(self, rows: np.ndarray, tps: Sequence[TP]) -> None:
        """TargetData and section durations of the given rows."""
        n = self.max_joints
        widths = {len(tp.positions) for tp in tps}
        if len(widths) == 1:  # the usual batch: one entity shape, one conversion
            w = widths.pop()
            pos = np.zeros((rows.size, n))
            vel = np.zeros((rows.size, n))
            pos[:, :w] = np.array([tp.positions for tp in tps], np.float64)
            vel[:, :w] = np.array([tp.velocities for tp in tps], np.float64)
        else:
            pos = np.zeros((rows.size, n))
            vel = np.zeros((rows.size, n))
            for i, tp in enumerate(tps):
                pos[i, : len(tp.positions)] = tp.positions
                vel[i, : len(tp.velocities)] = tp.velocities
        self.trg_pos[rows] = np.rint(pos * SCALE).astype(np.int64)
        self.trg_vel[rows] = np.rint(vel * SCALE).astype(np.int64)
        self.duration[rows] = np.rint(np.array([tp.duration_s for tp in tps]) * 1e9).astype(np.int64)

    def _alloc(self, key: tuple[int, int]) -> int:
        row = self._free.pop()
        self._row[key] = row
        self._key[row] = key
        return row

    def _link(self, row: int, kind: str, target: tuple[int, int]) -> None:
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
        target = (self._key_entity(row), int(self._next_id[row]))
        self._unwait(target, (row, "next"))
        if row in self._switch_id:
            self._unwait((target[0], self._switch_id[row]), (row, "switch"))

    def _unwait(self, target: tuple[int, int], waiter: tuple[int, str]) -> None:
        waiters = self._waiting.get(target)
        if waiters is not None:
            waiters.discard(waiter)
            if not waiters:  # no empty sets left behind: streaming would grow them forever
                del self._waiting[target]

    def _key_entity(self, row: int) -> int:
        return self._key[row][0]

    def effective_next(self, rows: np.ndarray) -> np.ndarray:
        """The row each row steps to: its TrajectorySwitcher entry, else its TPStepper link (NO_ROW: none)."""
        safe = np.maximum(rows, 0)
        nxt = np.where(self.switch_row[safe] != NO_ROW, self.switch_row[safe], self.next_row[safe])
        return np.where(rows == NO_ROW, NO_ROW, nxt)

    def row_of(self, robot: int, tp_id: int) -> int:
        row = self._row.get((self.entity_of(robot), tp_id))
        if row is None:
            raise Refused("unknown_tp", f"robot {robot} has no TP {tp_id} loaded")
        return row

    # --- TrajectorySwitcher ----------------------------------------------------------------------

    def set_switch(self, robot: int, tp_id: int, next_id: int) -> None:
        """After TP tp_id, go to next_id instead of its successor (it may be loaded later)."""
        row = self.row_of(robot, tp_id)
        e = self.entity_of(robot)
        self.unset_switch(robot, tp_id)
        self._switch_id[row] = next_id
        self._link(row, "switch", (e, next_id))

    def unset_switch(self, robot: int, tp_id: int) -> None:
        row = self.row_of(robot, tp_id)
        old = self._switch_id.pop(row, None)
        if old is not None:
            self._unwait((self.entity_of(robot), old), (row, "switch"))
        self.switch_row[row] = NO_ROW

    # --- registers ------------------------------------------------------------------------------

    def set_registers(self, robot: int, tp_id: int, next_time_ns: int) -> None:
        """Make the robot's entity head for TP tp_id and step on at next_time_ns (absolute)."""
        e = self.entity_of(robot)
        row = self.row_of(robot, tp_id)
        self.reg_tp[e] = row
        self.reg_next_time[e] = next_time_ns

    def clear_registers(self, robot: int) -> None:
        """The entity follows nothing: its robots are told to hold (velocity 0)."""
        e = self.entity_of(robot)
        self.reg_tp[e] = NO_ROW

    def current_tp(self, robot: int) -> int | None:
        row = int(self.reg_tp[self.entity_of(robot)])
        return None if row == NO_ROW else self._key[row][1]

    # --- one atomic update ------------------------------------------------------------------------

    def update(
        self,
        insert: Sequence[TP] = (),
        remove: Sequence[tuple[int, int]] = (),
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
        insert: Sequence[TP] = (),
        remove: Sequence[tuple[int, int]] = (),
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

        switches: (robot, branching TP, next TP or None to unset); registers: (robot, TP or None
        to clear, next_time_ns).  Returns how many TPs were removed.
        """
        # --- 1. checks (nothing they rely on changes meanwhile: robots only move) ---------------
        keys: list[tuple[int, int]] = []
        for i in range(0, len(insert), slice_size):
            keys += self._check_tps(insert[i : i + slice_size])
            yield
        if len(set(keys)) != len(keys):
            raise Refused("bad_request", "a TP appears twice in one batch")
        fresh = [i for i, k in enumerate(keys) if k not in self._row]
        if len(fresh) > len(self._free):
            free = len(self._free)
            why = f"{len(fresh)} new TPs, {free} of {self.capacity} places free (delete some first)"
            raise Refused("table_full", why)
        new_keys = set(keys)

        def exists(robot: int, tp_id: int) -> bool:
            key = (self.entity_of(robot), tp_id)
            return key in self._row or key in new_keys

        for robot, tp_id, _ in switches:
            if not exists(robot, tp_id):
                raise Refused("unknown_tp", f"switch at TP {tp_id} of robot {robot}: no such TP")
        moved: dict[int, int | None] = {}
        for robot, tp_id, _ in registers:
            if tp_id is not None and not exists(robot, tp_id):
                raise Refused("unknown_tp", f"registers of robot {robot}: no TP {tp_id}")
            moved[self.entity_of(robot)] = tp_id
        gone_keys: dict[tuple[int, int], int] = {}  # key -> row; a key named twice is one row
        for i in range(0, len(remove), slice_size * 4):
            for robot, tp_id in remove[i : i + slice_size * 4]:
                key = (self.entity_of(robot), tp_id)
                row = self._row.get(key)
                if row is not None:
                    gone_keys[key] = row
            yield
        gone_rows = list(gone_keys.values())
        gone = np.array(gone_rows, np.int64)
        for e, tp_id in moved.items():
            if tp_id is not None and (e, tp_id) in gone_keys:
                raise Refused("in_use", f"TP {tp_id} is both started and deleted")

        # --- 2. stage new TPs in fresh rows nothing links to yet (invisible) -------------------
        staged: dict[tuple[int, int], int] = {}
        waits: list[tuple[tuple[int, int], int]] = []
        try:
            for i in range(0, len(fresh), slice_size):
                idx = fresh[i : i + slice_size]
                rows = [self._free.pop() for _ in idx]
                for row, j in zip(rows, idx, strict=True):
                    staged[keys[j]] = row
                    self._key[row] = keys[j]
                    self._next_id[row] = insert[j].next_id
                self._write_rows(np.array(rows, np.int64), [insert[j] for j in idx])
                yield
            items = list(staged.items())
            for i in range(0, len(items), slice_size * 2):
                for key, row in items[i : i + slice_size * 2]:
                    target = (key[0], int(self._next_id[row]))
                    to = staged.get(target)
                    if to is None and target not in gone_keys:
                        to = self._row.get(target)
                    self.next_row[row] = NO_ROW if to is None else to
                    self.switch_row[row] = NO_ROW
                    if to is None:
                        waits.append((target, row))
                yield
            # --- 3. the flip: everything visible in one step ------------------------------------
            if gone.size:
                current = self.reg_tp[: self.entities].astype(np.int64)
                upcoming = self.effective_next(current)
                is_gone = np.zeros(self.capacity, bool)
                is_gone[gone] = True
                stays = np.ones(self.entities, bool)
                stays[list(moved)] = False
                hit = stays & (
                    ((current != NO_ROW) & is_gone[np.maximum(current, 0)])
                    | ((upcoming != NO_ROW) & is_gone[np.maximum(upcoming, 0)])
                )
                if hit.any():
                    e = int(np.flatnonzero(hit)[0])
                    raise Refused(
                        "in_use", f"a TP entity {e} is following is to be deleted; switch or stop it first"
                    )
        except BaseException:
            self._free.extend(staged.values())  # never visible: just give the rows back
            raise
        self._row.update(staged)
        for target, row in waits:
            self._waiting[target].add((row, "next"))
        for key in staged.keys() & self._waiting.keys():  # the few links that waited for these TPs
            for waiter, kind in self._waiting.pop(key):
                (self.next_row if kind == "next" else self.switch_row)[waiter] = staged[key]
        self.valid[list(staged.values())] = True
        replaced = [insert[i] for i, k in enumerate(keys) if k not in staged]
        if replaced:
            self._insert_checked(replaced)  # in place: rare, and small
        for robot, tp_id, nxt in switches:
            if nxt is None:
                self.unset_switch(robot, tp_id)
            else:
                self.set_switch(robot, tp_id, nxt)
        for robot, tp_id, next_time in registers:
            if tp_id is None:
                self.clear_registers(robot)
            else:
                self.set_registers(robot, tp_id, next_time)
        if not gone.size:
            return 0
        self.valid[gone] = False
        for arr, kind in ((self.next_row, "next"), (self.switch_row, "switch")):
            pointing = np.flatnonzero(self.valid & (arr != NO_ROW) & is_gone[np.maximum(arr, 0)])
            for w in pointing.tolist():
                target = self._key[int(arr[w])]
                arr[w] = NO_ROW
                self._waiting[target].add((w, kind))
        yield
        # --- 4. the deleted rows' bookkeeping, in slices ---------------------------------------
        unresolved = set(gone[self.next_row[gone] == NO_ROW].tolist())  # rows sitting in a wait list
        for i in range(0, len(gone_rows), slice_size * 4):
            for row in gone_rows[i : i + slice_size * 4]:
                if row in unresolved or row in self._switch_id:
                    self._forget_waits(row)  # both its link's and its switch's waits
                    self._switch_id.pop(row, None)
                del self._row[self._key[row]]
            yield
        self.next_row[gone] = NO_ROW
        self.switch_row[gone] = NO_ROW
        self._free.extend(gone_rows)
        return len(gone_rows)

    def _check_tps(self, tps: Sequence[TP]) -> list[tuple[int, int]]:
        keys = []
        for tp in tps:
            e = self.entity_of(tp.robot)
            n = int(self.entity_joints[e])
            if len(tp.positions) != n or len(tp.velocities) != n:
                raise Refused("bad_request", f"TP {tp.id} of robot {tp.robot}: {n} joint values expected")
            if not tp.duration_s > 0:
                raise Refused("bad_request", f"TP {tp.id}: section duration must be > 0")
            if not (0 <= tp.id < 2**32 and 0 <= tp.next_id < 2**32):
                raise Refused("bad_request", f"TP ids are u32 (got {tp.id} -> {tp.next_id})")
            keys.append((e, tp.id))
        return keys
