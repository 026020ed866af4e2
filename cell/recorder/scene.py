"""The arm as Rerun draws it: link geometry from the MJCF model, link poses from forward kinematics.

Each MJCF body becomes an entity robots/<name>/links/<body> whose Transform3D
is the body's pose in the robot's base frame (MuJoCo's FK of the joints);
its geoms are logged once, static, as capsules in the body's frame
(cylinders are drawn as capsules of the same length).  The robot's base sits
at a fixed offset so that several robots are side by side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
import rerun as rr

from cell.robot.arm import ArmModel
from cell.vision.camera import CameraSpec, camera_axes

_ROUND = (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER))


@dataclass(frozen=True)
class LinkGeometry:
    body: str
    lengths: list[float]
    radii: list[float]
    translations: list[list[float]]
    quaternions: list[list[float]]  # xyzw
    colors: list[list[int]]


def link_geometry(arm: ArmModel) -> list[LinkGeometry]:
    m = arm.model
    out = []
    for b in range(1, m.nbody):
        lengths, radii, trans, quats, colors = [], [], [], [], []
        for g in range(m.ngeom):
            if m.geom_bodyid[g] != b or int(m.geom_type[g]) not in _ROUND:
                continue
            radius, half = float(m.geom_size[g][0]), float(m.geom_size[g][1])
            w, x, y, z = (float(v) for v in m.geom_quat[g])
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, m.geom_quat[g])
            axis = rot.reshape(3, 3)[:, 2]
            start = m.geom_pos[g] - axis * half  # rerun's capsules run from the origin along +z
            lengths.append(2 * half)
            radii.append(radius)
            trans.append(start.tolist())
            quats.append([x, y, z, w])
            colors.append([int(255 * c) for c in m.geom_rgba[g][:3]])
        if lengths:
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
            out.append(LinkGeometry(name, lengths, radii, trans, quats, colors))
    return out


class ArmDrawer:
    """Logs one robot's links: the static geometry once, then poses for joint positions."""

    def __init__(self, arm: ArmModel, name: str, base: tuple[float, float, float]) -> None:
        self.arm, self.name, self.base = arm, name, base
        self.data = mujoco.MjData(arm.model)
        self.geometry = link_geometry(arm)
        self.body_ids = [
            mujoco.mj_name2id(arm.model, mujoco.mjtObj.mjOBJ_BODY, g.body) for g in self.geometry
        ]

    def log_static(self, rec: rr.RecordingStream) -> None:
        rec.log(f"robots/{self.name}", rr.Transform3D(translation=self.base), static=True)
        for g in self.geometry:
            rec.log(
                f"robots/{self.name}/links/{g.body}/geom",
                rr.Capsules3D(
                    lengths=g.lengths,
                    radii=g.radii,
                    translations=g.translations,
                    quaternions=[rr.Quaternion(xyzw=q) for q in g.quaternions],
                    colors=g.colors,
                ),
                static=True,
            )

    def poses(self, q: np.ndarray) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """(entity, translation, quaternion xyzw) of every link for joint positions q."""
        d = self.data
        d.qpos[:] = q
        mujoco.mj_kinematics(self.arm.model, d)
        out = []
        for g, b in zip(self.geometry, self.body_ids, strict=True):
            w, x, y, z = d.xquat[b]
            out.append((f"robots/{self.name}/links/{g.body}", d.xpos[b].copy(), np.array([x, y, z, w])))
        return out


def camera_rotation(spec: CameraSpec) -> np.ndarray:
    """The camera's orientation in Rerun's camera convention (RDF: x right, y down in the image, z the
    way it looks), as columns in its robot's base frame."""
    x, y, z = camera_axes(np.array(spec.axis))
    return np.column_stack([x, -y, -z])


def log_camera(rec: rr.RecordingStream, robot: str, spec: CameraSpec) -> None:
    """The vision service's camera as a frustum in the 3D view, where it stands in its robot's base
    frame and with its lens's field of view (static: it does not move)."""
    entity = f"robots/{robot}/camera"
    rec.log(entity, rr.Transform3D(translation=spec.position_m, mat3x3=camera_rotation(spec)), static=True)
    rec.log(
        entity,
        rr.Pinhole(
            fov_y=math.radians(spec.lens.fovy_deg(spec.height_px)),
            aspect_ratio=spec.width_px / spec.height_px,
            resolution=[spec.width_px, spec.height_px],
            image_plane_distance=0.1,
        ),
        static=True,
    )
