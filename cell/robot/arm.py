"""An arm model loaded into MuJoCo (from the registry, cell.models): joint limits and forward
kinematics.

The model is the one source of truth for the arm: the MuJoCo emulator
simulates it and everything else takes its kinematics from it through here.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import mujoco
import numpy as np

from cell.models import RobotModel, get
from cell.models.mjcf import mjcf


@dataclass(frozen=True)
class Limits:
    """Per-joint limits, SI units (rad, rad/s, rad/s^2, N m)."""

    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray
    torque: np.ndarray


class ArmModel:
    """One arm model, loaded once per process (see `arm_model`)."""

    def __init__(self, model: str = "ur5e") -> None:
        self.name = model
        self.spec: RobotModel = get(model)
        self.model = mujoco.MjModel.from_xml_string(mjcf(model))
        m = self.model
        self.joints = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, i) for i in range(m.njnt)]
        self.dof = m.njnt
        self.limits = Limits(
            q_min=m.jnt_range[:, 0].copy(),
            q_max=m.jnt_range[:, 1].copy(),
            v_max=m.numeric("joint_max_velocity").data.copy(),
            a_max=m.numeric("joint_max_acceleration").data.copy(),
            torque=m.actuator_forcerange[:, 1].copy(),
        )
        self.tool_site = m.site("tool").id
        self._data = mujoco.MjData(m)

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool flange position (m) and rotation matrix in the base frame for joint positions q."""
        d = self._data
        d.qpos[:] = q
        mujoco.mj_kinematics(self.model, d)
        return d.site_xpos[self.tool_site].copy(), d.site_xmat[self.tool_site].reshape(3, 3).copy()

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """The tool flange's positional Jacobian (3, dof) at q: m per rad of each joint."""
        m, d = self.model, self._data
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        jac = np.empty((3, m.nv))
        mujoco.mj_jacSite(m, d, jac, None, self.tool_site)
        return jac

    def tool_pose(self, q: np.ndarray) -> np.ndarray:
        """[x, y, z, qw, qx, qy, qz]: the tool flange pose for q."""
        pos, rot = self.fk(q)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, rot.ravel())
        return np.concatenate([pos, quat])


@cache
def arm_model(model: str = "ur5e") -> ArmModel:
    return ArmModel(model)
