"""Both sides in one process, period by period, with the data link simulated: fast and repeatable.

The same Side objects as the real-time run, exchanging the same samples, but
the link is a DelayLine in simulated time and nothing waits for the clock.
Each side hears a sample at the earliest one period after it was sent (what
the real link gives: the peer's packet of period k arrives during period k);
`delay` adds to that.  The tests use it, and the bench for its sweep over
delays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.rlink.packet import EventType
from cell.teleop import figures
from cell.teleop.delay import DelayLine
from cell.teleop.law import Gains, Mode
from cell.teleop.model import HOME, OBJECTS
from cell.teleop.operator import PUSHES, Operator
from cell.teleop.side import PERIOD_S, Side
from cell.teleop.wire import Role, Sample


@dataclass
class Run:
    local: Side
    remote: Side
    operator: Operator
    seconds: float

    def transparency(self) -> dict[str, float]:
        """The run's figures over the pushing (cell.teleop.figures)."""
        return figures.transparency(
            self.local.trace.since(0),
            self.remote.trace.since(0),
            self.operator.contact_t,
            self.operator.lift_t,
        )


def run(
    obj: str = "sponge",
    delay_s: float = 0.0,
    jitter_s: float = 0.0,
    gains: Gains | None = None,
    mode: Mode = Mode.MODIFIED,
    pushes: tuple[float, ...] = PUSHES,
    max_s: float = 20.0,
    coulomb_nm: float = 0.0,
    estop_at_s: float | None = None,
) -> Run:
    """The scripted experiment until the operator is done (or max_s of simulated time)."""
    op = Operator(np.array(HOME), pushes=pushes)
    cap = int(max_s / PERIOD_S) + 2
    local = Side(Role.LOCAL, gains=gains, operator=op, coulomb_nm=coulomb_nm, capacity=cap)
    remote = Side(Role.REMOTE, OBJECTS[obj], gains=gains, coulomb_nm=coulomb_nm, capacity=cap)
    to_remote: DelayLine[Sample] = DelayLine(delay_s + PERIOD_S, jitter_s, seed=1)
    to_local: DelayLine[Sample] = DelayLine(delay_s + PERIOD_S, jitter_s, seed=2)
    for side in (local, remote):
        if mode != Mode.MODIFIED:
            side.event(EventType.MODE, bytes((mode,)))
        side.event(EventType.START)
    n = 0
    while not op.done and n * PERIOD_S < max_s:
        now = n * PERIOD_S
        if estop_at_s is not None and now >= estop_at_s:
            local.event(EventType.ESTOP)
            remote.event(EventType.ESTOP)
            estop_at_s = None
        got_l, got_r = to_local.take(now + 1e-9), to_remote.take(now + 1e-9)
        out_l = local.tick(got_l[-1] if got_l else None)
        out_r = remote.tick(got_r[-1] if got_r else None)
        to_remote.put(now, out_l)
        to_local.put(now, out_r)
        n += 1
    return Run(local, remote, op, n * PERIOD_S)
