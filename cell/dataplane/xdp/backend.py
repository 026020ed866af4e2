"""The numpy backend's Tables and Pipeline, with their packet-path state living in the XDP maps.

The control plane is the same code: a TP insert, a switch, a register set or a drop writes the
same numpy arrays, only these arrays are the BPF maps the kernel program reads.  What the
packet path must see at once (a staged update's flip, a drop, a merge) is written behind the
program's gate (XdpProgram.close_gate), so the kernel sees it entirely or not at all.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np

from cell.dataplane.pipeline import ControlConstants, Pipeline
from cell.dataplane.tables import Tables
from cell.dataplane.xdp.libbpf import BpfError
from cell.dataplane.xdp.program import MAX_ENTITIES, MAX_JOINTS, XdpProgram


def _rebind(obj: object, views: dict[str, np.ndarray]) -> None:
    """Each attribute becomes its map view, keeping the value it had."""
    for name, view in views.items():
        view[...] = getattr(obj, name)
        setattr(obj, name, view)


class XdpTables(Tables):
    def __init__(self, program: XdpProgram, max_joints: int = MAX_JOINTS) -> None:
        if max_joints > MAX_JOINTS:
            raise BpfError(f"the XDP program holds {MAX_JOINTS} joints per entity ([dataplane] max_joints)")
        super().__init__(program.capacity, MAX_ENTITIES, max_joints)
        self.program = program
        self._depth = 0
        rb, st, en, rw, j = program.robots, program.status, program.entities, program.rows, max_joints
        _rebind(
            self,
            {
                "robot_entity": rb["entity"],
                "robot_joint0": rb["joint0"],
                "status_ns": rb["status_ns"],
                "status_seq": rb["status_seq"],
                "status_pos": st["pos"][:, :j],
                "status_vel": st["vel"][:, :j],
                "reg_tp": en["tp"],
                "reg_next_time": en["next_time"],
                "reg_stalled": en["stalled"],
                "reg_stall_ns": en["stall_ns"],
                "reg_dropped_ns": en["dropped_ns"],
                "reg_dropped_why": en["dropped_why"],
                "next_row": rw["next_row"],
                "switch_row": rw["switch_row"],
                "duration": rw["duration"],
                "trg_pos": rw["trg_pos"][:, :j],
                "trg_vel": rw["trg_vel"][:, :j],
            },
        )
        program.globals["max_joints"] = max_joints

    def flip_begin(self) -> None:
        if self._depth == 0:
            self.program.close_gate()
        self._depth += 1

    def flip_end(self) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.program.open_gate()

    @contextmanager
    def gated(self) -> Iterator[None]:
        """Writes the packet path must see all at once."""
        self.flip_begin()
        try:
            yield
        finally:
            self.flip_end()

    def _new_entity(self, robots: list[int], joints: list[int]) -> int:
        with self.gated():
            return super()._new_entity(robots, joints)


class XdpPipeline(Pipeline):
    """Pipeline whose registers, constants and stops are the XDP program's; process() is the kernel's."""

    t: XdpTables

    def __init__(self, tables: XdpTables, constants: ControlConstants) -> None:
        self.program = tables.program
        super().__init__(tables, constants)
        rb = self.program.robots
        views = {"reg_stop": rb["stop"], "stale_periods": rb["stale_periods"], "quiet_ns": rb["quiet_ns"]}
        _rebind(self, views)

    @staticmethod
    def check_fits(program: XdpProgram, constants: ControlConstants) -> None:
        """BpfError unless the maps were sized for these constants (an XDP program's sizes are fixed
        at load; a program that can resize its Transform tables, the native one, fits any n_bits)."""
        if len(constants.c1) == program.joints and getattr(program, "fit", None) is not None:
            return
        if constants.n_bits != program.n_bits or len(constants.c1) != program.joints:
            raise BpfError(
                f"the XDP maps hold Transform tables for n_bits={program.n_bits} and {program.joints} joints"
                f" (got n_bits={constants.n_bits}, {len(constants.c1)} joints): restart the data plane"
            )

    def install(self, built: tuple) -> None:
        program = self.program
        self.check_fits(program, built[0])
        with self.t.gated():
            fit = getattr(program, "fit", None)  # (NativeProgram's: it resizes its Transform tables)
            if fit is not None:
                fit(built[0].n_bits)
            super().install(built)
            size = program.joints * 2 * program.eps
            for bank, t in enumerate(
                (self.transform_curr_velocity, self.transform_trg_velocity, self.transform_diff_position)
            ):
                program.transform[bank * size : (bank + 1) * size] = t.stack.reshape(-1)
            lim, out = self.limit_velocity, program.limits
            n = lim.limits.size
            out["limit"][:n], out["neg"][:n] = lim.limits, lim.neg
            out["hi_v"][:n], out["hi_m"][:n] = lim.hi_v, lim.hi_m
            out["lo_v"][:n], out["lo_m"][:n] = lim.lo_v, lim.lo_m

    def set_stop_ramp(self, decel: Sequence[float] | np.ndarray, window_s: float) -> None:
        super().set_stop_ramp(decel, window_s)
        self.program.globals["stop_ramp"][: self.stop_ramp.size] = self.stop_ramp

    def stop(self, robots: Sequence[int], on: bool = True) -> None:
        super().stop(robots, on)
        self.program.globals["stopping"] = self.stopping

    def drop(self, entities: np.ndarray, now: int, why: int) -> None:
        with self.t.gated():
            super().drop(entities, now, why)

    def process(self, *args: object, **kwargs: object) -> None:
        raise RuntimeError("the XDP backend's packet path runs in the kernel")
