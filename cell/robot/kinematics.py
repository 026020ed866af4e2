"""Inverse kinematics on the arm's MJCF model (the same file the emulator simulates).

Damped least squares on MuJoCo's site Jacobian, started from the joints the
robot has now: the iteration follows the continuous branch of solutions
nearest to them, so a small pose change is a small joint change, never a
flip of elbow or wrist.  If that start does not converge, a few others are
tried and the converged solution nearest the current joints wins.
"""

from __future__ import annotations

import mujoco
import numpy as np

from cell.robot.arm import ArmModel, arm_model
from cell.robot.pose import rotation_error

POS_TOL = 1e-7  # m
ROT_TOL = 1e-7  # rad
_DAMPING = 1e-4
_MAX_STEP = 0.5  # rad per iteration, for joints far from the solution


class Unreachable(ValueError):
    """No joint positions put the tool at the pose, or only ones outside the joint limits."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


class Kinematics:
    def __init__(self, arm: ArmModel | None = None) -> None:
        self.arm = arm or arm_model()
        self.model = self.arm.model
        self.data = mujoco.MjData(self.model)
        self.site = self.arm.tool_site
        self._jp = np.zeros((3, self.model.nv))
        self._jr = np.zeros((3, self.model.nv))

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool flange position (m) and rotation matrix in the robot's base frame."""
        return self.arm.fk(q)

    def ik(self, pos: np.ndarray, rot: np.ndarray, near: np.ndarray, max_iter: int = 100) -> np.ndarray:
        """Joint positions putting the tool at (pos, rot), nearest to `near`; Unreachable if none."""
        near = np.asarray(near, np.float64)
        q, err = self._solve(pos, rot, near, max_iter)
        if err > 1e-5:  # a local minimum from the current joints (e.g. across a singularity): restart
            found = []
            for seed in self._seeds(near):
                qs, e = self._solve(pos, rot, seed, max_iter)
                if e <= 1e-5:
                    found.append(qs)
            if not found:
                reach = float(np.linalg.norm(pos))
                raise Unreachable(
                    f"no joint positions reach the pose ({reach * 1000:.0f} mm from the base; "
                    f"closest miss {err:.3g} m or rad)"
                )
            q = min(found, key=lambda s: float(np.abs(s - near).sum()))
        lim = self.arm.limits
        # the same joint angle may be reached 2 pi away: take the one nearest the current joints
        q = q - 2 * np.pi * np.round((q - near) / (2 * np.pi))
        bad = np.flatnonzero((q < lim.q_min - 1e-9) | (q > lim.q_max + 1e-9))
        if bad.size:
            j = int(bad[0])
            raise Unreachable(
                f"joint {self.arm.joints[j]} would need {np.degrees(q[j]):.1f} deg, beyond its limits "
                f"[{np.degrees(lim.q_min[j]):.0f}, {np.degrees(lim.q_max[j]):.0f}] deg"
            )
        return q

    def _solve(
        self, pos: np.ndarray, rot: np.ndarray, q0: np.ndarray, max_iter: int
    ) -> tuple[np.ndarray, float]:
        m, d = self.model, self.data
        q = q0.copy()
        err = np.inf
        for _ in range(max_iter):
            d.qpos[:] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            e_pos = pos - d.site_xpos[self.site]
            e_rot = rotation_error(rot, d.site_xmat[self.site].reshape(3, 3))
            err = max(float(np.abs(e_pos).max()), float(np.abs(e_rot).max()))
            if float(np.abs(e_pos).max()) < POS_TOL and float(np.abs(e_rot).max()) < ROT_TOL:
                break
            mujoco.mj_jacSite(m, d, self._jp, self._jr, self.site)
            jac = np.vstack([self._jp, self._jr])
            e = np.concatenate([e_pos, e_rot])
            dq = jac.T @ np.linalg.solve(jac @ jac.T + _DAMPING * np.eye(6), e)
            biggest = float(np.abs(dq).max())
            if biggest > _MAX_STEP:
                dq *= _MAX_STEP / biggest
            q += dq
        return q, err

    def _seeds(self, near: np.ndarray) -> list[np.ndarray]:
        """Other starts: the current joints with shoulder, elbow and wrist turned over."""
        seeds = []
        for flips in ((0, np.pi), (1, -np.pi / 2), (2, np.pi), (2, -np.pi), (4, np.pi), (3, np.pi)):
            s = near.copy()
            s[flips[0]] += flips[1]
            seeds.append(s)
        seeds.append(np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]))
        seeds.append(np.array([0.0, -np.pi / 2, -np.pi / 2, -np.pi / 2, np.pi / 2, 0.0]))
        return seeds
