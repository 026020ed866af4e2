"""The modular robot of the `modular` service, sans IO: the VDC arm, its motions and its modules'
health, advanced one 1 ms cycle at a time by whoever owns the clock (services/modular.py).

Motions are joint moves (minimum jerk, cell.modular.reference.joint_move), tool moves (one IK to
a joint goal) and the named references of the figures (pick-and-place, circle: from home, reached
first by a joint move).  One runs at a time; between them the arm holds where the last ended.

FDIR is the slides': a module's missing A is guessed from physical continuity and the arm goes
on; a module silent for `suspect_cycles` is suspect, one silent for `lost_cycles` is lost.  A lost
module stops the arm: the motion under way ends failed, saying which module, the arm holds where
it is (the lost module on its brake) and motions are refused until the module is back.  Unplugging
a module (`unplug`) takes it off the network, as pulling its cable would.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from cell.modular.loop import Faults, Link, VdcArm
from cell.modular.reference import CYCLE_NS, Q_HOME, Reference, circle, joint_move, pick_and_place
from cell.modular.vdc import WHERE_MASTER, Gains
from cell.robot.arm import arm_model
from cell.robot.kinematics import Kinematics, Unreachable

NAMED: dict[str, Callable[[], Reference]] = {"pick-and-place": pick_and_place, "circle": circle}


class ModuleState(StrEnum):
    RUNNING = "running"
    SUSPECT = "suspect"  # silent some cycles: its messages guessed
    LOST = "lost"  # silent past lost_cycles: the arm stopped
    UNPLUGGED = "unplugged"  # taken off the network (`unplug`)
    JOINING = "joining"  # found by the master, being configured or syncing its clock (the SnP cycle's)


STATES = list(ModuleState)  # (a module's state as a counter: its index here)


class MotionRefused(Exception):
    """A motion the robot does not take now, and why (said to the one who asked)."""


@dataclass
class Motion:
    path: str
    ref: Reference
    then: Reference | None = None  # a named reference run after this move (its approach)
    k: int = 0
    errors_mm: list[float] = field(default_factory=list)
    guessed_at_start: int = 0
    failed: str = ""  # why it ended before its end ("" ended on it)

    @property
    def ended(self) -> bool:
        return self.failed != "" or (self.k >= len(self.ref.t) and self.then is None)


@dataclass(frozen=True)
class Ended:
    """A motion that ended, as its requester is told."""

    path: str
    cycles: int
    tool_error_mm_max: float
    tool_error_mm_rms: float
    guessed: int
    failed: str


class ArmRobot:
    """What the modular robot's engines share (the `modular` service drives either): its modules'
    names, the motions it takes and why it refuses one, its counters.  ModularRobot runs the VDC
    cycles in this process; cell.modular.processes.CycleRobot has them run by the SnP cycle's
    master and modules in processes of their own."""

    NAMES = tuple(f"j{i + 1}" for i in range(6))
    transport = "memory"  # ([modular] transport)

    def __init__(self, where: tuple[str, ...]) -> None:
        self.where = where
        self.period_ns = CYCLE_NS
        nan = np.full(6, np.nan)
        self.clock_offsets_us, self.module_cycle_us = nan, nan.copy()  # (the SnP cycle's only)
        self.tool_ref = np.zeros(3)  # where the reference has the tool now
        self.states = [ModuleState.RUNNING] * 6
        self.motion: Motion | None = None
        self.stopped = ""  # why motions are refused ("": taken)
        self.failed = ""  # why the engine cannot go on ("": it can; the service then fails, to be restarted)
        self.cycles = 0
        self.cycle_ns_sum = 0
        self.cycle_ns_max = 0
        self._kin = Kinematics(arm_model("ur5e"))
        self._named: dict[str, Reference] = {}

    # -- what the engines give ----------------------------------------------------------------------
    @property
    def q(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def tool(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def guessed_by(self) -> np.ndarray:
        """Per module, its messages (or exchanges) guessed so far."""
        raise NotImplementedError

    @property
    def phase_us(self) -> np.ndarray:
        """The last cycle's A, B, C, D arithmetic, us (where it runs in this process)."""
        return np.zeros(0)

    def frames(self) -> np.ndarray:
        """Each joint's origin and the tool, (7, 3) m: the arm as a line."""
        raise NotImplementedError

    def move(
        self, *, joints: list[float] | None = None, tool: list[float] | None = None, path: str = "",
        speed: float = 1.0,
    ) -> Motion:  # fmt: skip
        """Start a motion (MotionRefused if the arm is stopped, busy, or the goal is bad)."""
        raise NotImplementedError

    def unplug(self, name: str) -> None:
        raise NotImplementedError

    def plug(self, name: str) -> None:
        """The module back: it runs again from its next A; once every module runs, the arm takes
        motions again (from where it held)."""
        raise NotImplementedError

    def cycle(self) -> Ended | None:
        """The clock's side: one cycle (or what the processes reported since); the motion that ended
        in it, if one did."""
        raise NotImplementedError

    def close(self) -> None:
        """Whatever the engine runs besides this process, ended."""

    # -- what users ask ---------------------------------------------------------------------------
    def module(self, name: str) -> int:
        if name not in self.NAMES:
            raise MotionRefused(f"no module {name!r}: the modules are {', '.join(self.NAMES)}")
        return self.NAMES.index(name)

    def named(self, path: str) -> Reference:
        """A named reference (computed once: a few hundred ms of IK)."""
        if path not in NAMED:
            raise MotionRefused(f"no path {path!r}: the named paths are {', '.join(NAMED)}")
        if path not in self._named:
            self._named[path] = NAMED[path]()
        return self._named[path]

    def plan(
        self, joints: list[float] | None, tool: list[float] | None, path: str, speed: float
    ) -> tuple[str, Reference, Reference | None]:
        """A motion's name, its joint move from here and the named reference after it (if any);
        MotionRefused if the arm is stopped, busy, or the goal is bad."""
        if self.stopped:
            raise MotionRefused(self.stopped)
        if self.motion is not None:
            raise MotionRefused(f"the modular robot is moving ({self.motion.path}): one motion at a time")
        if not speed > 0 or not np.isfinite(speed):
            raise MotionRefused(f"speed must be a positive number of rad/s (got {speed})")
        here = self.q
        then = None
        if path:
            then = self.named(path)
            goal = then.q[0]
        elif joints is not None and len(joints) > 0:
            goal = np.asarray(joints, float)
            if goal.shape != (6,) or not np.all(np.isfinite(goal)):
                raise MotionRefused(f"joints must be 6 finite numbers in rad (got {list(joints)})")
            if np.abs(goal).max() > 2 * np.pi:
                raise MotionRefused("joints must be within +-2 pi rad")
        elif tool is not None and len(tool) > 0:
            p = np.asarray(tool, float)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise MotionRefused(f"tool must be x, y, z in m (got {list(tool)})")
            _, rot = self._kin.fk(here)
            try:
                goal = self._kin.ik(p, rot, here)
            except Unreachable as exc:
                raise MotionRefused(f"the tool position {tuple(p.tolist())} m: {exc}") from None
        else:
            raise MotionRefused("a motion needs joints, a tool position or a path")
        return path or ("joints" if joints else "tool"), joint_move(here, goal, speed), then

    @property
    def cycle_us_mean(self) -> float:
        """What a cycle took on average (ModularRobot: the VDC arithmetic, its messages and the
        arm's step; CycleRobot: a module's [A, B, C, D] exchange)."""
        return self.cycle_ns_sum / max(self.cycles, 1) / 1e3

    def counters(self) -> dict[str, float]:
        """For the service's heartbeat (`cell status` reads the modules from them)."""
        out: dict[str, float] = {
            "modular.cycles": self.cycles,
            "modular.cycle_us_mean": self.cycle_us_mean,
            "modular.cycle_us_max": self.cycle_ns_max / 1e3,
        }
        for name, state, guessed in zip(self.NAMES, self.states, self.guessed_by, strict=True):
            out[f"modular.{name}.state"] = STATES.index(state)
            out[f"modular.{name}.guessed"] = int(guessed)
        return out


class ModularRobot(ArmRobot):
    """The VDC arm (cell.modular.loop.VdcArm) in this process, one cycle() at a time."""

    def __init__(
        self,
        q0: np.ndarray = Q_HOME,
        *,
        loss: float = 0.0,
        where: tuple[str, ...] = (WHERE_MASTER,) * 6,
        suspect_cycles: int = 3,
        lost_cycles: int = 20,
        seed: int = 1,
        link: Link | None = None,
        adapt: float = 0.0,
    ) -> None:
        """adapt: each module's inertial parameters adapted with this gain (Gains.adapt)."""
        super().__init__(where)
        faults = Faults(loss=loss, seed=seed)
        self.vdc = VdcArm(np.asarray(q0, float), faults, where, Gains(adapt=adapt), link=link)
        self.transport = "memory" if link is None else "snp"
        self.suspect_cycles, self.lost_cycles = suspect_cycles, lost_cycles
        self.silent = np.zeros(6, dtype=np.int64)  # cycles in a row without the module's A
        self.hold = self.vdc.arm.q  # where the arm holds between motions
        self.tool_ref = self.vdc.arm.tool_position()

    @property
    def q(self) -> np.ndarray:
        return self.vdc.arm.q

    @property
    def tool(self) -> np.ndarray:
        return self.vdc.arm.tool_position()

    @property
    def guessed_by(self) -> np.ndarray:
        return self.vdc.guessed_by

    @property
    def phase_us(self) -> np.ndarray:
        return self.vdc.phase_ns / 1e3

    def move(
        self,
        *,
        joints: list[float] | None = None,
        tool: list[float] | None = None,
        path: str = "",
        speed: float = 1.0,
    ) -> Motion:
        """Start a motion (MotionRefused if the arm is stopped, busy, or the goal is bad)."""
        name, ref, then = self.plan(joints, tool, path, speed)
        m = Motion(name, ref, then, guessed_at_start=int(self.vdc.guessed_by.sum()))
        self.motion = m
        return m

    def unplug(self, name: str) -> None:
        i = self.module(name)
        self.vdc.unplug(i)
        self.states[i] = ModuleState.UNPLUGGED

    def plug(self, name: str) -> None:
        """The module back: it runs again from its next A; once every module runs, the arm takes
        motions again (from where it held)."""
        i = self.module(name)
        self.vdc.plug(i)
        self.silent[i] = 0
        self.states[i] = ModuleState.RUNNING

    # -- the clock's side ---------------------------------------------------------------------------
    def cycle(self) -> Ended | None:
        """One 1 ms cycle; the motion that ended in it, if one did."""
        m = self.motion
        if m is not None and m.k >= len(m.ref.t) and m.then is not None:  # its approach done: the path
            m.ref, m.then, m.k = m.then, None, 0
        if m is not None:
            ref = m.ref
            k = m.k
            q_d, qd_d, qdd_d, tool_d = ref.q[k], ref.qd[k], ref.qdd[k], ref.tool[k]
        else:
            q_d, qd_d, qdd_d, tool_d = self.hold, np.zeros(6), np.zeros(6), None
        t0 = time.perf_counter_ns()
        self.vdc.cycle(q_d, qd_d, qdd_d)
        took = time.perf_counter_ns() - t0
        self.cycles += 1
        self.cycle_ns_sum += took
        self.cycle_ns_max = max(self.cycle_ns_max, took)
        self._fdir()
        if m is None:
            self.tool_ref = self.vdc.arm.tool_position(self.hold)
            return None
        self.tool_ref = tool_d
        m.errors_mm.append(float(np.linalg.norm(self.vdc.arm.tool_position() - tool_d)) * 1e3)
        m.k += 1
        if self.stopped:
            m.failed = self.stopped
        if not m.ended:
            return None
        self.motion = None
        if not m.failed:
            self.hold = ref.q[-1]
        e = np.array(m.errors_mm)
        return Ended(
            m.path,
            len(e),
            float(e.max()),
            float(np.sqrt(np.mean(e**2))),
            int(self.vdc.guessed_by.sum()) - m.guessed_at_start,
            m.failed,
        )

    def _fdir(self) -> None:
        for i in range(6):
            if self.vdc.a_lost[i]:
                self.silent[i] += 1
            else:
                self.silent[i] = 0
            if self.states[i] is ModuleState.UNPLUGGED:
                continue
            if self.silent[i] >= self.lost_cycles:
                self.states[i] = ModuleState.LOST
            elif self.silent[i] >= self.suspect_cycles:
                self.states[i] = ModuleState.SUSPECT
            else:
                self.states[i] = ModuleState.RUNNING
        gone = [
            f"{self.NAMES[i]} {s}"
            for i, s in enumerate(self.states)
            if s is ModuleState.LOST or (s is ModuleState.UNPLUGGED and self.silent[i] >= self.lost_cycles)
        ]
        if gone and not self.stopped:
            self.stopped = f"module {', '.join(gone)}: the arm holds where it stood until it is back"
            self.hold = self.vdc.arm.q
        elif not gone and self.stopped and all(s is ModuleState.RUNNING for s in self.states):
            self.stopped = ""  # every module back: motions are taken again (from where it holds)

    def frames(self) -> np.ndarray:
        d = self.vdc.arm.data
        return np.vstack([d.xanchor, self.vdc.arm.tool_position()[None, :]])
