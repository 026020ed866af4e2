"""The modular robot of seed 002: six MR1 joint modules (each a motor, a link and its electronics)
in a chain, torque-driven, in MuJoCo; and each module's rigid body as Virtual Decomposition Control
sees it.

The modules take the UR5e's lengths and masses (cell.models.ur: UR's published DH parameters
and link masses; 850 mm reach, 5 kg payload): module i is the UR5e's link i with its motor and
electronics lumped in, its joint a torque motor with the UR5e joint size's reflected rotor inertia
(armature), viscous friction and torque limit.  MuJoCo simulates it at TIMESTEP; the controllers
only read its joints and write its motor torques.

Spatial vectors are Featherstone's, in each module's own body frame (origin on its joint axis, z
along it): motion [w; v], force [n; f].  ^iX_{i-1} maps motion from the parent's frame to the
module's, and its transpose maps force back.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import mujoco
import numpy as np

from cell.models.mjcf import mjcf

MODEL = "ur5e"  # the registry model whose geometry and masses the modules take
TIMESTEP = 0.00025  # s: MuJoCo's step (four a 1 ms control cycle)
GRAVITY = np.array([0.0, 0.0, -9.81])
AXIS = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # a module's joint: rotation about its body's z


def skew(p: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])


def rz(q: float) -> np.ndarray:
    c, s = np.cos(q), np.sin(q)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def motion_transform(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """^cX_p for a child frame at `pos` in its parent's, turned `rot` (the child's axes in the
    parent's): motion [w; v] from the parent's frame to the child's."""
    rt = rot.T
    x = np.zeros((6, 6))
    x[:3, :3] = rt
    x[3:, 3:] = rt
    x[3:, :3] = -rt @ skew(pos)
    return x


def crm(v: np.ndarray) -> np.ndarray:
    """v x (motion cross product) as a matrix."""
    m = np.zeros((6, 6))
    w, lin = skew(v[:3]), skew(v[3:])
    m[:3, :3] = w
    m[3:, 3:] = w
    m[3:, :3] = lin
    return m


def crf(v: np.ndarray) -> np.ndarray:
    """v x* (force cross product): -crm(v)^T."""
    return -crm(v).T


def spatial_inertia(mass: float, com: np.ndarray, inertia_com: np.ndarray) -> np.ndarray:
    """The rigid body's 6x6 inertia about its frame's origin (com and the rotational inertia about
    the centre of mass in the body's axes)."""
    c = skew(com)
    out = np.zeros((6, 6))
    out[:3, :3] = inertia_com + mass * c @ c.T
    out[:3, 3:] = mass * c
    out[3:, :3] = mass * c.T
    out[3:, 3:] = mass * np.eye(3)
    return out


@dataclass(frozen=True)
class Body:
    """One module's rigid body and motor, as its own electronics knows them."""

    pos: np.ndarray  # its joint's origin in the parent module's frame
    rot: np.ndarray  # its frame's axes in the parent's at q = 0
    inertia: np.ndarray  # (6, 6) about its frame's origin
    armature: float  # the motor's reflected rotor inertia, kg m^2
    damping: float  # the joint's viscous friction, N m s / rad
    torque_max: float  # N m

    def transform(self, q: float) -> np.ndarray:
        """^iX_{i-1} at joint position q."""
        return motion_transform(self.rot @ rz(q), self.pos)


def _quat_matrix(quat: np.ndarray) -> np.ndarray:
    m = np.empty(9)
    mujoco.mju_quat2Mat(m, quat)
    return m.reshape(3, 3)


def bodies(model: mujoco.MjModel) -> tuple[Body, ...]:
    """Each module's Body, read from the MuJoCo model (the parameters a module reports when it is
    plugged in: the master configures itself from them)."""
    out = []
    for j in range(model.njnt):
        b = int(model.jnt_bodyid[j])
        rot_i = _quat_matrix(model.body_iquat[b])  # (the inertial frame's axes in the body's)
        inertia_com = rot_i @ np.diag(model.body_inertia[b]) @ rot_i.T
        out.append(
            Body(
                pos=model.body_pos[b].copy(),
                rot=_quat_matrix(model.body_quat[b]),
                inertia=spatial_inertia(float(model.body_mass[b]), model.body_ipos[b].copy(), inertia_com),
                armature=float(model.dof_armature[j]),
                damping=float(model.dof_damping[j]),
                torque_max=float(model.actuator_ctrlrange[j, 1]),
            )
        )
    return tuple(out)


@cache
def _xml() -> str:
    return mjcf(MODEL, torque=True, timestep=TIMESTEP)


class ModularArm:
    """The six-module arm in MuJoCo: joints read, motor torques written, stepped."""

    def __init__(self, q0: np.ndarray | None = None) -> None:
        self.model = mujoco.MjModel.from_xml_string(_xml())
        self.data = mujoco.MjData(self.model)
        self.dof = self.model.njnt
        self.bodies = bodies(self.model)
        self.tool = self.model.site("tool").id
        self._scratch = mujoco.MjData(self.model)
        if q0 is not None:
            self.data.qpos[:] = q0
            mujoco.mj_forward(self.model, self.data)

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos.copy()

    @property
    def qd(self) -> np.ndarray:
        return self.data.qvel.copy()

    def step(self, tau: np.ndarray, steps: int = 1) -> None:
        """`steps` MuJoCo steps with the motors at tau (clipped to their limits by the model)."""
        self.data.ctrl[:] = tau
        for _ in range(steps):
            mujoco.mj_step(self.model, self.data)

    def tool_position(self, q: np.ndarray | None = None) -> np.ndarray:
        if q is None:
            return self.data.site_xpos[self.tool].copy()
        d = self._scratch
        d.qpos[:] = q
        mujoco.mj_kinematics(self.model, d)
        return d.site_xpos[self.tool].copy()

    def inverse_dynamics(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """MuJoCo's own inverse dynamics (mj_inverse): the joint torques for qdd at (q, qd),
        armature and friction included; the centralised controller's model."""
        d = self._scratch
        d.qpos[:], d.qvel[:], d.qacc[:] = q, qd, qdd
        mujoco.mj_inverse(self.model, d)
        return d.qfrc_inverse.copy()
