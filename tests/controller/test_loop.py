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
