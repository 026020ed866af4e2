"""A trajectory as the bus carries it (controller.follow's JointTrajectory, cell/v1/controller.proto):
the message from arrays, and the Trajectory from the message, both ways in one place."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cell.trajectory.model import Trajectory, TrajectoryError
from cell.v1 import controller_pb2


def to_message(
    robot: str,
    t: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray | None = None,
    qdd: np.ndarray | None = None,
    joint_names: Sequence[str] = (),
    name: str = "",
) -> controller_pb2.JointTrajectory:
    """Points of one robot as a message (rows a point; joint_names empty: the robot's order)."""
    return controller_pb2.JointTrajectory(
        robot=robot,
        joint_names=list(joint_names),
        t=np.asarray(t, np.float64).tolist(),
        positions=np.asarray(q, np.float64).ravel().tolist(),
        velocities=[] if qd is None else np.asarray(qd, np.float64).ravel().tolist(),
        accelerations=[] if qdd is None else np.asarray(qdd, np.float64).ravel().tolist(),
        name=name,
    )


def from_message(m: controller_pb2.JointTrajectory, robot_joints: Sequence[str]) -> Trajectory:
    """The message as a Trajectory in the robot's joint order; TrajectoryError if it cannot be one
    (the reason names the first offending point)."""
    n, dof = len(m.t), len(m.joint_names) or len(robot_joints)
    if not m.positions:
        raise TrajectoryError("no positions")

    def rows(values: Sequence[float], what: str) -> np.ndarray | None:
        if not values:
            return None
        if len(values) != n * dof:
            raise TrajectoryError(f"{what}: {len(values)} values for {n} points of {dof} joints")
        return np.array(values, np.float64).reshape(n, dof)

    q = rows(m.positions, "positions")
    assert q is not None  # (there are positions: checked above)
    return Trajectory.build(
        np.array(m.t, np.float64),
        q,
        rows(m.velocities, "velocities"),
        rows(m.accelerations, "accelerations"),
        joint_names=list(m.joint_names) or None,
        robot_joints=robot_joints,
        name=m.name,
    )
