"""The robot-model registry: each UR e-Series model's MuJoCo model is its published DH chain, with its
published limits; the cell takes a robot's model from its own config entry."""

from __future__ import annotations

import numpy as np
import pytest

from cell.config import ConfigError, load_config
from cell.models import MODELS, get
from cell.robot.arm import arm_model

UR_E = ("ur3e", "ur5e", "ur10e", "ur16e")


def dh_fk(name: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The flange pose from the DH parameters alone (standard convention): no MuJoCo."""
    m = get(name)
    t = np.eye(4)
    for qi, a, d, alpha in zip(q, m.a, m.d, m.alpha, strict=True):
        c, s, ca, sa = np.cos(qi), np.sin(qi), np.cos(alpha), np.sin(alpha)
        t = t @ np.array(
            [[c, -s * ca, s * sa, a * c], [s, c * ca, -c * sa, a * s], [0, sa, ca, d], [0, 0, 0, 1]]
        )
    return t[:3, 3], t[:3, :3]


def test_the_ur_e_series_is_registered() -> None:
    assert set(UR_E) <= set(MODELS)
    assert [get(n).joints for n in UR_E] == [6, 6, 6, 6]
    with pytest.raises(KeyError, match=r"unknown robot model 'ur99'.*ur10e"):
        get("ur99")


@pytest.mark.parametrize("name", UR_E)
def test_the_mujoco_model_is_the_published_dh_chain(name: str) -> None:
    arm = arm_model(name)
    rng = np.random.default_rng(7)
    for q in [np.zeros(6), *rng.uniform(-np.pi, np.pi, (20, 6))]:
        pos, rot = arm.fk(q)
        want_pos, want_rot = dh_fk(name, q)
        assert np.abs(pos - want_pos).max() < 1e-9, (name, q)
        assert np.abs(rot - want_rot).max() < 1e-9, (name, q)


def test_the_ur5e_flange_at_zero_is_where_ur_puts_it() -> None:
    # UR5e at all joints zero: x = a2 + a3, y = -(d4 + d6), z = d1 - d5 (UR's DH table)
    pos, _ = arm_model("ur5e").fk(np.zeros(6))
    assert np.allclose(pos, [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997], atol=1e-12)


@pytest.mark.parametrize("name", UR_E)
def test_limits_masses_and_drives_come_from_the_record(name: str) -> None:
    spec, arm = get(name), arm_model(name)
    assert np.allclose(arm.limits.v_max, spec.v_max) and np.allclose(arm.limits.a_max, spec.a_max)
    assert np.allclose(arm.limits.torque, spec.torque)
    assert np.allclose(arm.limits.q_min, spec.q_min) and np.allclose(arm.limits.q_max, spec.q_max)
    assert np.isclose(arm.model.body_mass.sum(), sum(spec.mass))
    # reach: the datasheet's (to the wrist, with its housing) is a little beyond the two long links
    pos, _ = arm.fk(np.zeros(6))
    assert pos[0] == pytest.approx(spec.a[1] + spec.a[2], abs=1e-12)
    assert 0.85 * spec.reach_m < -pos[0] < spec.reach_m


def test_the_bigger_arms_are_slower_and_stronger_at_the_base() -> None:
    ur5e, ur10e, ur3e = get("ur5e"), get("ur10e"), get("ur3e")
    assert np.degrees(ur10e.v_max[0]) == pytest.approx(120) and np.degrees(ur5e.v_max[0]) == pytest.approx(
        180
    )
    assert ur10e.torque[:3] == (330.0, 330.0, 150.0) and ur5e.torque == (150.0,) * 3 + (28.0,) * 3
    assert np.degrees(ur3e.v_max[5]) == pytest.approx(360)


def test_each_robot_takes_its_own_model_and_an_unknown_one_is_a_config_error() -> None:
    robots = [
        {"id": 1, "name": "r1", "skill_port": 41001, "model": "ur5e"},
        {"id": 2, "name": "r2", "skill_port": 41002, "model": "ur10e"},
    ]
    cfg = load_config(overrides={"robots": robots})
    assert [r.model for r in cfg.robots] == ["ur5e", "ur10e"]
    with pytest.raises(ConfigError, match=r"robots\[1\]\.model: unknown robot model 'ur11e' \(known: .*ur5e"):
        load_config(overrides={"robots": [robots[0], {**robots[1], "model": "ur11e"}]})


def test_the_controller_plans_each_robot_with_its_own_model() -> None:
    from cell.controller.controller import Controller
    from cell.dataplane.plane import stop_decel

    robots = [
        {"id": 1, "name": "r1", "skill_port": 41001, "model": "ur5e"},
        {"id": 2, "name": "r2", "skill_port": 41002, "model": "ur10e"},
    ]
    cfg = load_config(overrides={"robots": robots})
    ctl = Controller(None, cfg)  # type: ignore[arg-type]  (no bus: planning state only)
    v1, v2 = ctl.track("r1").limits.v_max, ctl.track("r2").limits.v_max
    assert v2[0] < v1[0] and np.isclose(v2[0], np.radians(120))  # the UR10e's base is slower
    q = np.array([0.3, -1.2, 1.0, -1.4, -1.5, 0.2])
    assert np.allclose(ctl.pose_of("r2", q)[0], dh_fk("ur10e", q)[0])
    assert np.allclose(ctl.pose_of("r1", q)[0], dh_fk("ur5e", q)[0])
    merged = ctl.book.limits_of([1, 2])
    assert np.allclose(merged.v_max, np.concatenate([v1, v2]))
    # one stop ramp serves every robot: it brakes no joint harder than any model allows
    assert np.allclose(
        stop_decel(cfg), np.minimum(get("ur5e").a_max, get("ur10e").a_max) * cfg.rlink.stop_decel
    )
