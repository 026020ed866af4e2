"""What the controller's motions are made of: the segments it loads, the tracks it drives, the
results and refusals it answers with (the schedule's and the engine's shared types)."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from enum import Enum, StrEnum

import numpy as np

from cell.controller.plan import MotionLimits
from cell.controller.tps import Sections
from cell.trajectory.motion import Motion

_ID_SPACE = 2**32  # TP ids (uint32) wrap around
# a holding TP's section: how often it steps onto itself.  A motion's final hold once took its last
# section's duration, which can be a fraction of a millisecond: then the resting robot's hold stepped
# on every status packet, a storm of resubmits costing the data plane CPU for nothing
HOLD_S = 1.0


class MotionStopped(Exception):
    """The motion was cut short by a stop (or replaced by a re-plan)."""


class NotAtGoal(Exception):
    """The motion ran to its end but the robot was not read standing at its goal: never a `done`."""


@dataclass
class MotionResult:
    start_ns: int  # data-plane clock
    end_ns: int
    q_end: np.ndarray  # where the plan ends (rad)


@dataclass
class FollowResult(MotionResult):
    t0_ns: int = 0  # when the trajectories' time 0 was (after the approach to their first points)
    tps_per_s: float = 0.0  # the TPs a second of trajectory its fitting used (the busiest robot's)
    deviation_mm: float = 0.0  # the largest distance of the modelled tool from the plan (fit_led)


@dataclass
class Switch:
    """The last re-plan: where it branched, and the start state it predicted there."""

    branch_tp: int
    t_branch_ns: int  # data-plane clock
    lead_ms: float  # how long before the branch the switch entry was in place
    q_pred: np.ndarray
    v_pred: np.ndarray


@dataclass
class Segment:
    """A motion as loaded: its TP ids and its start on the data-plane clock."""

    start_ns: int
    motion: Motion
    sections: Sections
    ids: list[int]  # one per section, then the final hold (a self-loop at the end position)
    tick0: int | None = None  # the robot's status period in its window at start_ns (None: unknown)
    robot: int = 0  # whose tick grid start_ns is on (with tick0)
    episode: int = 0  # TPs loaded at a time, if not the controller's `episode` (dense TPs: more)

    def __post_init__(self) -> None:
        s = self.sections
        assert len(self.ids) == len(s) + 1
        tp_q = s.q if s.p_trg is None else s.p_trg
        self.q = np.vstack([tp_q, s.q[-1:]])  # the TPs' positions, velocities and durations
        self.v = np.vstack([s.v_ff, np.zeros_like(s.v_ff[-1:])])
        self.d = np.append(s.duration, HOLD_S)

    def t_ns(self, k: int) -> int:
        """When section k ends (data-plane clock)."""
        return self.start_ns + int(self.sections.t_end[k] * 1e9)

    @property
    def end_ns(self) -> int:
        return self.t_ns(len(self.sections) - 1)


class MotionState(Enum):
    """Where a track's last motion stands (Track.state)."""

    IDLE = "idle"  # never moved by this controller
    MOVING = "moving"  # its motion is being streamed
    ARRIVED = "arrived"  # its last motion ran to its end; it holds there
    STOPPED = "stopped"  # its last motion ended early (a stop, the Responsive Link, the data plane lost)
    FAILED = "failed"  # its last motion's streaming failed (Track.failure says why)


class MotionKind(StrEnum):
    JOINTS = "joints"  # a joint-space motion (to joints, or to a pose by IK)
    LINEAR = "linear"  # the tool along a straight line


@dataclass(frozen=True, slots=True)
class Goal:
    """A motion as it was asked for, kept until it ends: what resume() plans again after a stop."""

    kind: MotionKind
    target: np.ndarray | tuple[np.ndarray, np.ndarray]  # joints, or (position, rotation) for LINEAR
    speed: float
    fine: bool


@dataclass
class Track:
    """One entity as the controller drives it: a robot, or robots merged to move as one."""

    robot: int  # the id the data plane knows the entity by (the first robot of a merged one)
    robots: list[int]
    limits: MotionLimits
    next_id: int = 1
    q_hold: np.ndarray | None = None  # where it holds after its last motion (None: not started)
    loaded: list[int] = field(default_factory=list)  # TP ids of this track in the tables
    segment: Segment | None = None
    task: asyncio.Task | None = None  # the motion being streamed (in the engine's task group)
    failure: BaseException | None = None  # what ended the streaming of its last motion, if it failed
    inflight: set[asyncio.Future] = field(default_factory=set)  # its updates, which always finish
    starting: asyncio.Lock = field(default_factory=asyncio.Lock)  # motions start one after another
    stop_reason: str | None = None  # why its last motion ended early (for MotionStopped)
    generation: int = 0  # bumped when its TPs are lost: bookkeeping of older updates is void
    epoch: int = 0  # bumped by every stop or loss: an `arrive` waiting across one answers stopped
    loaded_ns: int = 0  # when (data-plane clock) its current TPs went in: older drops are old news
    loads: int = 0  # registers set by this controller so far (a flush decided before one must not follow it)

    @property
    def joints(self) -> int:
        return self.limits.v_max.size

    @property
    def moving(self) -> bool:
        return self.task is not None and not self.task.done()

    @property
    def state(self) -> MotionState:
        if self.moving:
            return MotionState.MOVING
        if self.failure is not None:
            return MotionState.FAILED
        if self.stop_reason:
            return MotionState.STOPPED
        return MotionState.IDLE if self.task is None and self.q_hold is None else MotionState.ARRIVED

    def take_ids(self, n: int) -> list[int]:
        ids = [(self.next_id + i) % _ID_SPACE for i in range(n)]
        self.next_id = (self.next_id + n) % _ID_SPACE
        return ids


# --- motions prepared ahead (cell.controller.prepared) ------------------------------------------------


@dataclass
class Armed:
    """Motions loaded and held, started by fire()."""

    planned: list[tuple[Track, Segment, int]]  # (track, its motion, its hold TP)
    period_ns: int  # the holds step together every period from their registers' time
    at_ns: int  # that time (data-plane clock): the holds' steps are at_ns + k period
    armed_ns: int = field(default_factory=time.monotonic_ns)


@dataclass
class LoopRun:
    """A loop under way: its laps, and the exit the controller sets (end_loop())."""

    track: Track
    q0: np.ndarray  # where each lap starts and ends
    start_ns: int
    lap_ns: int
    last_id: int  # the lap's last TP: its switch entry leads out
    exit_id: int
    laps: int  # 0: until ended
    done: asyncio.Future[int] = field(default_factory=lambda: asyncio.get_running_loop().create_future())

    def lap_end_ns(self, n: int) -> int:
        return self.start_ns + n * self.lap_ns


@dataclass
class Alternate:
    """One prepared branch: from TP k of the main motion to another goal."""

    k: int
    segment: Segment


# --- table entries -----------------------------------------------------------------------------------
