"""The loop model's run in C (cell/controller/loop.c) against its numpy reference."""

from __future__ import annotations

import numpy as np

from cell.bench.loopsim import Loop
from cell.controller import loop as loopmod
from cell.controller.plan import plan_joint
from cell.controller.tps import cut

Q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def test_the_c_loop_model_is_the_numpy_one_bit_for_bit() -> None:
    assert loopmod._native() is not None  # (cc is installed by `make test`)
    model = Loop("dataplane", "kinematic").loop
    rng = np.random.default_rng(39)
    for trial in range(200):
        q, v, p = rng.uniform(-3, 3, (3, 6))
        held = rng.uniform(-4, 4, 6)
        v_trg = rng.uniform(-10, 10, (int(rng.integers(1, 48)), 6) if trial % 2 else 6)
        tick, n = int(rng.integers(0, 100)), int(rng.integers(1, 80))
        got = model.run(q, v, held, tick, n, p, v_trg)
        want = model.run_numpy(q, v, held, tick, n, p, v_trg)
        for g, w in zip(got, want, strict=True):
            assert np.array_equal(g, np.broadcast_to(w, g.shape)), (trial, tick, n)


def test_a_motions_tps_are_the_same_fitted_in_c_or_numpy(monkeypatch) -> None:
    sim = Loop("dataplane", "kinematic")
    motion = plan_joint(Q0, Q0 + np.array([0.5, -0.3, 0.2, 0.1, -0.4, 0.6]), sim.limits.scaled(0.7))
    fast = cut(motion, 10, sim.c2 / sim.c1, sim.loop, tick0=1)
    monkeypatch.setattr(loopmod, "_native", lambda: None)  # (no compiler: numpy runs it)
    slow = cut(motion, 10, sim.c2 / sim.c1, sim.loop, tick0=1)
    assert np.array_equal(fast.v_ff, slow.v_ff) and np.array_equal(fast.q, slow.q)


def test_the_c_fit_is_the_python_fit_step_for_step() -> None:
    """loop_fit (a whole motion in one C call) against fit_numpy (Python around the C run): the same
    v_trg and the same states on the way, bit for bit, from any start state, tick and section lengths."""
    sim = Loop("dataplane", "kinematic")
    model = sim.loop
    rng = np.random.default_rng(7)
    for trial in range(60):
        k = int(rng.integers(1, 40))
        t_end = np.cumsum(rng.uniform(0.004, 0.2, k))
        q0 = rng.uniform(-2, 2, 6)
        q_end = q0 + np.cumsum(rng.uniform(-0.05, 0.05, (k, 6)), axis=0)
        v0 = rng.uniform(-0.5, 0.5, 6)
        held0 = None if trial % 3 == 0 else rng.uniform(-1, 1, 6)
        tick0 = int(rng.integers(0, 8))
        got, got_trace = model.fit(q_end, t_end, q0, v0, tick0, held0)
        want, want_trace = model.fit_numpy(q_end, t_end, q0, v0, tick0, held0)
        assert np.array_equal(got, want), trial
        for name in ("q", "v", "held", "periods"):
            assert np.array_equal(getattr(got_trace, name), getattr(want_trace, name)), (trial, name)
