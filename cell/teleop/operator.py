"""The operator on the local side: a hand of impedance Z_l that pushes the object several times.

The hand is a spring and damper (stiffness and damping of a relaxed human arm
holding a handle) between where the operator means the hand to be and the
local tip.  The operator moves that point down until the push is felt to
reach its target force, holds it a moment, eases off until only a light
touch remains, rests, and pushes again, as in the paper's Fig. 15: the
operator acts on what is felt, so every push ends near its target whatever
the object.  After the last push the hand goes back up to where it started.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

PUSHES = (4.0, 6.0, 5.0, 6.0)  # N: the target of each push


class Phase(Enum):
    APPROACH = "approach"  # moving down until the object is felt
    PRESS = "press"
    HOLD = "hold"
    EASE = "ease"  # coming back up to a light touch
    REST = "rest"
    LIFT = "lift"  # after the last push, back to the start
    DONE = "done"


@dataclass
class Operator:
    start: np.ndarray  # (2,) m: the hand's starting point (the local tip's)
    pushes: tuple[float, ...] = PUSHES
    stiffness: float = 400.0  # N/m
    damping: float = 15.0  # N s/m
    speed: float = 0.03  # m/s: how fast the hand moves
    touch_n: float = 0.5  # N: felt as touching
    hold_s: float = 0.25
    rest_s: float = 0.35
    lift_m: float = 0.005  # m: above the start, at the end
    phase: Phase = Phase.APPROACH
    hand: np.ndarray = field(init=False)
    push: int = 0  # index of the current push
    contact_t: float | None = None  # when the object was first felt (s)
    lift_t: float | None = None  # when the last push was over (s): [contact_t, lift_t) is the pushing
    hand_v: float = 0.0  # m/s: the hand's vertical speed in the last period
    _since: float = 0.0

    def __post_init__(self) -> None:
        self.hand = np.array(self.start, dtype=float)

    @property
    def done(self) -> bool:
        return self.phase == Phase.DONE

    def force(self, t: float, dt: float, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The hand's force on the local tip at time t (s), given the tip's position and velocity."""
        f = self.stiffness * (self.hand - x) - self.damping * v
        f[1] += self.damping * self.hand_v
        felt = -f[1]  # pushing down is a negative force on the tip: felt as a positive push
        step = self.speed * dt
        z0, p = self.hand[1], self.phase
        if p == Phase.APPROACH:
            self.hand[1] -= step
            if felt >= self.touch_n:
                self.contact_t = t
                self._to(Phase.PRESS, t)
        elif p == Phase.PRESS:
            self.hand[1] -= step
            if felt >= self.pushes[self.push]:
                self._to(Phase.HOLD, t)
        elif p == Phase.HOLD:
            if t - self._since >= self.hold_s:
                self._to(Phase.EASE, t)
        elif p == Phase.EASE:
            self.hand[1] += step
            if felt <= self.touch_n:
                self.push += 1
                if self.push == len(self.pushes):
                    self.lift_t = t
                self._to(Phase.REST if self.push < len(self.pushes) else Phase.LIFT, t)
        elif p == Phase.REST:
            if t - self._since >= self.rest_s:
                self._to(Phase.PRESS, t)
        elif p == Phase.LIFT:
            self.hand[1] = min(self.hand[1] + step, self.start[1] + self.lift_m)
            if self.hand[1] >= self.start[1] + self.lift_m:
                self._to(Phase.DONE, t)
        self.hand_v = (self.hand[1] - z0) / dt
        return f

    def _to(self, phase: Phase, t: float) -> None:
        self.phase, self._since = phase, t
