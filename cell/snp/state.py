"""The values SnP queries ask for, from what the cell publishes on the bus.

Each robot's joint positions, velocities and commanded velocities come from
its ground truth (truth/<name>), kept as a history; planned positions from
the controller's plans (plan/<name>).  A value at a past time is interpolated
from the history; at a future time it is predicted from the plan plus the
robot's current deviation from it, as the in-network paper predicts a
robot's state (Sec. 6.1):

    p(t) = p_plan(t) + (p_now - p_plan(now)) + (v_now - v_plan(now)) (t - now)

or, with no plan, extrapolated from the last state.  Times are ns on the
cell clock (the master's CLOCK_REALTIME); the bus carries CLOCK_MONOTONIC,
converted with the offset between the two clocks of this host.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from cell.snp.packet import Item, Quantity, split_item_id

HISTORY = 2000  # samples kept per robot (20 s at 100 Hz)


def realtime_offset_ns() -> int:
    """CLOCK_REALTIME - CLOCK_MONOTONIC on this host (the cell clock from the bus's clock)."""
    a = time.monotonic_ns()
    r = time.time_ns()
    b = time.monotonic_ns()
    return r - (a + b) // 2


@dataclass
class _Robot:
    joints: int
    t: deque[int] = field(default_factory=lambda: deque(maxlen=HISTORY))  # cell clock ns
    q: deque[np.ndarray] = field(default_factory=lambda: deque(maxlen=HISTORY))
    qd: deque[np.ndarray] = field(default_factory=lambda: deque(maxlen=HISTORY))
    cmd: deque[np.ndarray] = field(default_factory=lambda: deque(maxlen=HISTORY))
    plan_t: np.ndarray | None = None  # cell clock ns
    plan_q: np.ndarray | None = None
    plan_v: np.ndarray | None = None


class CellState:
    def __init__(self, offset_ns: int | None = None) -> None:
        self.offset_ns = realtime_offset_ns() if offset_ns is None else offset_ns
        self.robots: dict[int, _Robot] = {}

    # --- what comes in ---------------------------------------------------------------------------

    def add_robot(self, robot: int, joints: int) -> None:
        self.robots.setdefault(robot, _Robot(joints))

    def observe(self, robot: int, t_mono_ns: int, q: np.ndarray, qd: np.ndarray, cmd: np.ndarray) -> None:
        r = self.robots.get(robot)
        if r is None:
            return
        t = t_mono_ns + self.offset_ns
        if r.t and t <= r.t[-1]:
            return
        r.t.append(t)
        r.q.append(np.asarray(q, np.float64))
        r.qd.append(np.asarray(qd, np.float64))
        r.cmd.append(np.asarray(cmd, np.float64))

    def set_plan(self, robot: int, t_mono_ns: np.ndarray, q: np.ndarray, v: np.ndarray) -> None:
        r = self.robots.get(robot)
        if r is not None and len(t_mono_ns):
            r.plan_t, r.plan_q, r.plan_v = np.asarray(t_mono_ns) + self.offset_ns, q, v

    # --- StateSource --------------------------------------------------------------------------------

    def known(self, item: int) -> bool:
        robot, quantity, joint = split_item_id(item)
        r = self.robots.get(robot)
        return r is not None and quantity in tuple(Quantity) and joint < r.joints and bool(r.t)

    def refine(self, item: Item) -> None:
        """An input item: a measurement the asker has, newer than what the bus brought."""
        robot, quantity, joint = split_item_id(item.id)
        r = self.robots.get(robot)
        if (
            r is None
            or not r.t
            or item.timestamp <= r.t[-1]
            or quantity not in (Quantity.POSITION, Quantity.VELOCITY)
        ):
            return
        q, qd = r.q[-1].copy(), r.qd[-1].copy()
        (q if quantity == Quantity.POSITION else qd)[joint] = item.value
        r.t.append(item.timestamp)
        r.q.append(q)
        r.qd.append(qd)
        r.cmd.append(r.cmd[-1])

    def value(self, item: int, t_ns: int) -> float:
        robot, quantity, joint = split_item_id(item)
        r = self.robots[robot]
        if quantity == Quantity.PLANNED_POSITION:
            return float(self._plan(r, t_ns, joint)[0]) if r.plan_t is not None else float(r.q[-1][joint])
        t_last = r.t[-1]
        if t_ns <= t_last:  # the past: interpolated from the history
            series = {Quantity.POSITION: r.q, Quantity.VELOCITY: r.qd, Quantity.COMMANDED_VELOCITY: r.cmd}[
                Quantity(quantity)
            ]
            ts = np.fromiter(r.t, np.float64, len(r.t))
            vals = np.fromiter((s[joint] for s in series), np.float64, len(series))
            return float(np.interp(t_ns, ts, vals))
        dt = (t_ns - t_last) / 1e9  # the future: predicted
        p_now, v_now = float(r.q[-1][joint]), float(r.qd[-1][joint])
        if quantity == Quantity.COMMANDED_VELOCITY:
            return float(r.cmd[-1][joint])
        if r.plan_t is not None:
            p_plan_now, v_plan_now = self._plan(r, t_last, joint)
            p_plan_t, v_plan_t = self._plan(r, t_ns, joint)
            if quantity == Quantity.POSITION:
                return p_plan_t + (p_now - p_plan_now) + (v_now - v_plan_now) * dt
            return v_plan_t + (v_now - v_plan_now)
        return p_now + v_now * dt if quantity == Quantity.POSITION else v_now

    @staticmethod
    def _plan(r: _Robot, t_ns: int, joint: int) -> tuple[float, float]:
        assert r.plan_t is not None and r.plan_q is not None and r.plan_v is not None
        return (
            float(np.interp(t_ns, r.plan_t, r.plan_q[:, joint])),
            float(np.interp(t_ns, r.plan_t, r.plan_v[:, joint])),
        )
