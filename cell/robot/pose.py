"""Poses at the product's edges: (x, y, z, yaw, pitch, roll) in mm and degrees, as in the Adept
protocol, with V+'s Z-Y-Z Euler angles (yaw about z, pitch about the new y, roll about the new z).
Inside the cell poses are SI: a position in m and a 3x3 rotation matrix.
"""

from __future__ import annotations

import math

import numpy as np

_SINGULAR = 1e-9  # |sin(pitch)| below this: yaw and roll turn about the same axis; roll is set to 0


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def from_adept(pose: tuple[float, ...] | list[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y, z mm, yaw, pitch, roll deg) -> (position m, rotation matrix)."""
    if len(pose) != 6 or not all(math.isfinite(v) for v in pose):
        raise ValueError(f"a pose is 6 finite numbers (x, y, z, yaw, pitch, roll), got {list(pose)}")
    x, y, z, yaw, pitch, roll = (float(v) for v in pose)
    rot = rot_z(math.radians(yaw)) @ rot_y(math.radians(pitch)) @ rot_z(math.radians(roll))
    return np.array([x, y, z]) / 1000.0, rot


def to_adept(pos: np.ndarray, rot: np.ndarray) -> tuple[float, ...]:
    """(position m, rotation matrix) -> (x, y, z mm, yaw, pitch, roll deg), pitch in [0, 180]."""
    r = np.asarray(rot)
    sp = math.hypot(r[0, 2], r[1, 2])
    pitch = math.atan2(sp, r[2, 2])
    if sp > _SINGULAR:
        yaw = math.atan2(r[1, 2], r[0, 2])
        roll = math.atan2(r[2, 1], -r[2, 0])
    elif r[2, 2] > 0:  # pitch 0: R = Rz(yaw + roll)
        yaw, roll = math.atan2(r[1, 0], r[0, 0]), 0.0
    else:  # pitch 180 (a tool pointing down): R = Rz(yaw) Ry(pi) with roll 0
        yaw, roll = math.atan2(-r[1, 0], -r[0, 0]), 0.0
    p = np.asarray(pos, np.float64) * 1000.0
    return (float(p[0]), float(p[1]), float(p[2]), *(math.degrees(a) for a in (yaw, pitch, roll)))


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """The rotation vector (axis * angle, base frame) that turns `current` into `target`."""
    r = target @ current.T
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-12:
        return 0.5 * axis  # small angles: the skew part is the rotation vector
    if math.pi - angle < 1e-6:  # near a half turn the skew part vanishes: take the axis from r + I
        m = (r + np.eye(3)) / 2.0
        axis = m[int(np.argmax(np.diag(m)))]
        return axis / np.linalg.norm(axis) * angle
    return axis / (2.0 * math.sin(angle)) * angle


def slerp(r0: np.ndarray, r1: np.ndarray, s: float) -> np.ndarray:
    """The rotation a fraction s of the way from r0 to r1 (about one fixed axis)."""
    return from_rotvec(rotation_error(r1, r0) * s) @ r0


def from_rotvec(rv: np.ndarray | list[float] | tuple[float, ...]) -> np.ndarray:
    """The rotation matrix of a rotation vector (axis * angle, rad): UR's pose orientation."""
    w = np.asarray(rv, np.float64)
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def to_rotvec(rot: np.ndarray) -> np.ndarray:
    """The rotation vector of a rotation matrix (angle in [0, pi])."""
    return rotation_error(rot, np.eye(3))
