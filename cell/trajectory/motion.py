"""What a planned motion is to everything that runs one: its positions and velocities at any time.

Below both the controller's planners (cell.controller.plan: ruckig, lines, stops, loops) and the
trajectories planned elsewhere (cell.trajectory.model), which the controller cuts into TPs alike.
"""

from __future__ import annotations

import numpy as np


class Motion:
    """A planned motion: positions and velocities at any time from its start (0) to `duration`."""

    duration: float
    dof: int
    knots: np.ndarray | None = None  # times its sections should end at (a trajectory's points), if any

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError
