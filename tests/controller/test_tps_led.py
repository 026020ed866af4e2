"""Led TPs fitted to a plan (cell.controller.tps.fit_led): the loop model's robot held within the bound
of the plan at every status period, as few TPs as that takes, and a plan past one TP a command
window refused with where."""

from __future__ import annotations

import numpy as np
import pytest

from cell.controller.loop import LoopModel
from cell.controller.plan import PlanError
from cell.controller.tps import Led, fit_led
from cell.robot.arm import arm_model
from cell.trajectory.model import TimedMotion, Trajectory

ARM = arm_model("ur5e")
Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
AMP = np.array([0.5, -0.3, 0.3, 0.4, 0.4, 0.6])
LOOP = LoopModel(c1=np.ones(6), c2=np.full(6, 2.0), v_max=np.full(6, np.pi), a_max=ARM.limits.a_max, n_bits=8)
W = LOOP.window * LOOP.status_s


def out_and_back(seconds: float, pps: float = 40.0, amp: np.ndarray = AMP) -> Led:
    t = np.linspace(0.0, seconds, round(pps * seconds) + 1)
    q = Q0 + amp * (1 - np.cos(2 * np.pi * t / seconds))[:, None] / 2
    return Led(TimedMotion(Trajectory.build(t, q)), W)


def tool_error(q: np.ndarray):
    jac = np.stack([ARM.jacobian(x) for x in q])
    return lambda dq: np.linalg.norm(np.einsum("mij,mj->mi", jac, dq), axis=1)


def modelled_tool_error_mm(motion: Led, s) -> np.ndarray:
    """The loop model's robot under the TPs, at every status period, against the plan (by FK)."""
    ns = np.diff(np.rint(s.t_end / LOOP.status_s).astype(np.int64), prepend=0)
    path = LOOP.path(
        np.append(ns, LOOP.window),
        np.vstack([s.q, s.q[-1:]]),
        np.vstack([s.v_ff, np.zeros((1, 6))]),
        motion.sample(np.array([0.0]))[0][0],
        np.zeros(6),
        np.zeros(6),
    )
    plan = motion.sample((np.arange(len(path)) + 1) * LOOP.status_s)[0]
    return (
        np.array([np.linalg.norm(ARM.fk(a)[0] - ARM.fk(b)[0]) for a, b in zip(path, plan, strict=True)]) * 1e3
    )


@pytest.mark.parametrize("bound_mm", [0.05, 0.02, 0.005])
def test_the_modelled_tool_stays_within_the_bound_at_every_status_period(bound_mm: float) -> None:
    motion = out_and_back(3.0)
    s = fit_led(motion, LOOP, 10.0, tool_error, bound_mm / 1e3)
    err = modelled_tool_error_mm(motion, s)
    assert err.max() <= bound_mm * 1.01, err.max()  # (the Jacobian's first order: 1 % of slack)
    assert s.deviation_m * 1e3 == pytest.approx(err.max(), rel=0.02)
    assert s.lead_s == W and np.allclose(s.t_end[-1], 3.0) and s.q[-1] == pytest.approx(Q0)
    # whole command windows (the last section ends on the plan's end)
    windows = s.duration[:-1] / W
    assert np.allclose(windows, np.round(windows)) and np.round(windows).min() >= 1


def test_a_slower_plan_or_a_looser_bound_takes_fewer_tps() -> None:
    fast = fit_led(out_and_back(3.0), LOOP, 10.0, tool_error, 0.02e-3)
    slow = fit_led(out_and_back(6.0), LOOP, 10.0, tool_error, 0.02e-3)
    loose = fit_led(out_and_back(3.0), LOOP, 10.0, tool_error, 0.1e-3)
    assert len(slow) / 6.0 < 0.75 * len(fast) / 3.0
    assert len(loose) < 0.6 * len(fast)
    assert slow.duration.max() > 2 * W  # (longer sections where the plan allows them)


def test_a_plan_past_one_tp_a_command_window_is_refused_with_where() -> None:
    # 4.6 rad/s^2 on every joint (within the arm's 5): one window's chord alone strays 0.03 mm, and
    # the drives' ramps between the windows' commands lag it more
    with pytest.raises(PlanError, match=r"turns too fast for one TP a command window at t = 0\.\d+"):
        fit_led(out_and_back(0.8, 250.0, np.full(6, 0.15)), LOOP, 10.0, tool_error, 0.02e-3)
    fit_led(out_and_back(1.6, 250.0, np.full(6, 0.15)), LOOP, 10.0, tool_error, 0.02e-3)  # (half as fast)


def test_a_led_motion_stands_a_window_then_runs_its_plan() -> None:
    motion = out_and_back(3.0)
    q, v = motion.sample(np.array([0.0, W / 2, W, W + 1.5]))
    inner_q, inner_v = motion.inner.sample(np.array([0.0, 1.5]))
    assert np.allclose(q[:3], inner_q[0]) and not v[:2].any()
    assert np.allclose(q[3], inner_q[1]) and np.allclose(v[3], inner_v[1])
    assert motion.duration == pytest.approx(3.0 + W)
