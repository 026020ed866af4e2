"""Which controller has each robot: the data plane's record of take-overs (sans I/O).

A controller that starts, or recovers from losing the data plane, takes its robots over: it flushes
whatever the tables hold for them.  A second controller on the same data plane (a script's own
beside the cell's `controller` service) used to lose its motion to such a flush unseen: its robots
stopped mid-move and its next updates went on loading TPs onto tables another had taken.

Here a robot's owner is the controller that last flushed it (said in the data plane's state, so a
watching controller sees its robot go).  A controller that had loaded a robot before another
controller flushed it has lost it: its updates to that robot are refused (`taken`) until it takes
the robot over itself.  A controller that never loaded the robot before the flush may load it:
controllers still share robots (the script's beside the service's), but none goes on unseen on
tables another took.  Controller 0 is a tool (a bench writing TPs, a test pulling a robot's TPs
from under its controller): never refused, and its flush takes nothing over.
"""

from __future__ import annotations

from collections.abc import Iterable

KEEP = 16  # controllers remembered as having lost a robot (each restart of a controller adds one)


class Ownership:
    """The owners and losers of each robot, updated by each table update that was applied."""

    def __init__(self) -> None:
        self.owner: dict[int, int] = {}  # robot -> the controller that last flushed it
        self._loaded: dict[int, dict[int, None]] = {}  # robot -> controllers that loaded it since
        self._lost: dict[int, dict[int, None]] = {}  # robot -> controllers that lost it (oldest first)

    def refused(self, controller: int, robots: Iterable[int]) -> list[int]:
        """The robots among these that `controller` lost to another's take-over."""
        if not controller:
            return []
        return sorted({r for r in robots if controller in self._lost.get(r, {})})

    def applied(self, controller: int, robots: Iterable[int], flushed: Iterable[int]) -> None:
        """An update of `controller` applied: it flushed `flushed` (taking them over) and loaded,
        removed, switched or set registers of `robots`."""
        if not controller:
            return
        for r in flushed:
            lost = self._lost.pop(r, {}) | self._loaded.pop(r, {})
            lost.pop(controller, None)
            if lost:
                self._lost[r] = dict.fromkeys(list(lost)[-KEEP:])
            self.owner[r] = controller
            self._loaded[r] = {controller: None}
        for r in robots:
            self._loaded.setdefault(r, {})[controller] = None
