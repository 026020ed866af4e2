"""TP columns <-> their protobuf form (TrajectoryPoints, TpKeys): one place for both directions."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from cell.dataplane.tables import TPBatch
from cell.v1 import dataplane_pb2


def encode_tps(batch: TPBatch, out: dataplane_pb2.TrajectoryPoints) -> None:
    mask = np.arange(batch.positions.shape[1]) < batch.joints[:, None]
    out.robot_id.extend(batch.robot.tolist())
    out.id.extend(batch.id.tolist())
    out.next_id.extend(batch.next_id.tolist())
    out.duration_s.extend(batch.duration_s.tolist())
    out.joints.extend(batch.joints.tolist())
    out.positions.extend(batch.positions[mask].tolist())
    out.velocities.extend(batch.velocities[mask].tolist())


def decode_tps(msg: dataplane_pb2.TrajectoryPoints) -> TPBatch:
    """ValueError if the columns disagree (lengths, joint counts)."""
    return TPBatch.from_flat(
        np.array(msg.robot_id, np.int64),
        np.array(msg.id, np.int64),
        np.array(msg.next_id, np.int64),
        np.array(msg.duration_s, np.float64),
        np.array(msg.joints, np.int64),
        np.array(msg.positions, np.float64),
        np.array(msg.velocities, np.float64),
    )


def encode_keys(keys: Iterable[tuple[int, int]] | np.ndarray, out: dataplane_pb2.TpKeys) -> None:
    pairs = np.asarray(keys if isinstance(keys, np.ndarray) else list(keys), np.int64).reshape(-1, 2)
    out.robot_id.extend(pairs[:, 0].tolist())
    out.id.extend(pairs[:, 1].tolist())


def decode_keys(msg: dataplane_pb2.TpKeys) -> np.ndarray:
    """(n, 2) array of (robot, TP id); ValueError if the columns differ in length."""
    robots, ids = np.array(msg.robot_id, np.int64), np.array(msg.id, np.int64)
    if robots.size != ids.size:
        raise ValueError(f"TpKeys: {robots.size} robot ids, {ids.size} TP ids")
    return np.stack([robots, ids], axis=1)
