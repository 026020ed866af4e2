"""The arm's own MJCF model: forward kinematics against the published DH table, and its servos."""

from __future__ import annotations

import numpy as np
import pytest

from cell.robot.arm import arm_model
from cell.robot.backends import KinematicArms, MujocoArms

# Universal Robots' published UR5e DH parameters: an independent check of the MJCF
DH_A = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0]
DH_D = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996]
DH_ALPHA = [np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0]


def dh_fk(q: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    for th, a, d, al in zip(q, DH_A, DH_D, DH_ALPHA, strict=True):
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
        T = T @ np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]]
        )
    return T


def test_forward_kinematics_matches_the_dh_table() -> None:
    arm = arm_model()
    rng = np.random.default_rng(0)
    for q in [np.zeros(6), *rng.uniform(-np.pi, np.pi, (200, 6))]:
        pos, rot = arm.fk(q)
        T = dh_fk(q)
        assert np.allclose(pos, T[:3, 3], atol=1e-9)
        assert np.allclose(rot, T[:3, :3], atol=1e-9)


def test_zero_pose_reach_is_the_published_one() -> None:
    pos, _ = arm_model().fk(np.zeros(6))
    # stretched out along -x: a2 + a3, with the wrist offsets d4 (y) and d1 - d5 (z)
    assert pos == pytest.approx([-0.8172, -0.2329, 0.0628], abs=1e-4)


def test_limits_come_from_the_model() -> None:
    lim = arm_model().limits
    assert np.allclose(lim.v_max, np.pi) and np.allclose(lim.a_max, 5.0)
    assert lim.torque.tolist() == [150, 150, 150, 28, 28, 28]
    assert lim.q_max[2] == pytest.approx(np.pi) and lim.q_max[0] == pytest.approx(2 * np.pi)


POSES = {
    "working": [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0],
    "stretched": [0.0] * 6,
    "twisted": [1.0, -0.5, -1.0, 0.5, 1.2, -2.0],
}


@pytest.mark.parametrize("pose", POSES.values(), ids=POSES.keys())
@pytest.mark.parametrize("v", [0.4, -1.2])
def test_mujoco_arm_tracks_a_constant_velocity_within_1_percent(pose: list[float], v: float) -> None:
    arm = arm_model()
    for joint in range(6):
        arms = MujocoArms(arm, np.array([pose]), watchdog=3)
        arms.drives.target[0, joint] = v
        for _ in range(400):  # ramp (|v| / 5 rad/s^2 <= 0.24 s) and settle
            arms.step(0.002)
        measured = []
        for _ in range(100):
            arms.step(0.002)
            measured.append(arms.qd[0, joint])
        assert np.mean(measured) == pytest.approx(v, rel=0.01)
        assert np.max(np.abs(np.array(measured) - v)) < 0.01 * abs(v)
        assert np.abs(np.delete(arms.qd[0], joint)).max() < 0.01 * abs(v)  # the others hold


def test_mujoco_arm_holds_its_pose_against_gravity() -> None:
    arm = arm_model()
    arms = MujocoArms(arm, np.array([POSES["stretched"]]), watchdog=3)
    for _ in range(500):
        arms.step(0.002)
    assert np.abs(arms.q[0] - 0.0).max() < 1e-4  # no sag: the drives compensate gravity


def test_kinematic_arm_integrates_and_stops_at_joint_limits() -> None:
    arms = KinematicArms(arm_model(), np.array([[0.0, 0, 3.0, 0, 0, 0]]), watchdog=3)
    arms.drives.target[0, :] = 1.0
    for _ in range(500):  # 1 s: 0.2 s ramp, then 1 rad/s
        arms.step(0.002)
    assert arms.q[0, 0] == pytest.approx(0.9, abs=1e-9)  # 0.1 rad in the ramp + 0.8 rad
    assert arms.q[0, 2] == pytest.approx(np.pi)  # the elbow stopped at its end stop
    assert arms.qd[0, 2] == 0.0 and arms.limit_hits >= 1
