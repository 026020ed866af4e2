"""Virtual Decomposition Control of the six-module arm (cell.modular): its recursions against
MuJoCo's own inverse dynamics, its distributed variants against each other, and the arm tracking a
0.5 m/s path through lost and late messages."""

from __future__ import annotations

import numpy as np
import pytest

from cell.modular.arm import ModularArm
from cell.modular.loop import Faults, track_centralised, track_vdc
from cell.modular.reference import circle
from cell.modular.vdc import WHERE_LOCAL, WHERE_NEIGHBOUR, A, Gains, Master, Module


@pytest.fixture(scope="module")
def ref():
    return circle(radius=0.08, speed=0.5)


def test_vdc_without_feedback_is_the_arms_inverse_dynamics() -> None:
    """The master's forward and backward recursions around each module's own rigid-body dynamics,
    plus the module's motor terms, give MuJoCo's mj_inverse torques for any state: the same model,
    decomposed (gravity through the base's acceleration)."""
    arm = ModularArm()
    none = Gains(lam=0.0, body_rot=0.0, body_lin=0.0, joint=0.0)
    master, modules = Master(arm.bodies, none), [Module(b, none) for b in arm.bodies]
    rng = np.random.default_rng(5)
    for _ in range(25):
        q, qd, qdd = rng.uniform(-3, 3, 6), rng.uniform(-2, 2, 6), rng.uniform(-8, 8, 6)
        b = master.forward([A(x, y) for x, y in zip(q, qd, strict=True)], q, qd, qdd)
        d = master.backward([m.net_force(bi) for m, bi in zip(modules, b, strict=True)])
        tau = [di.tau_r + m.body.armature * bi.qdd_r + m.body.damping * bi.qd_r
               for di, m, bi in zip(d, modules, b, strict=True)]  # fmt: skip
        assert np.allclose(tau, arm.inverse_dynamics(q, qd, qdd), rtol=0, atol=1e-9)


@pytest.mark.slow
def test_the_arm_tracks_within_the_aims_and_loss_is_guessed_not_retried(ref) -> None:
    clean = track_vdc(ref)
    assert clean.tool_error_mm_max <= 2.0 and not clean.guessed
    lossy = track_vdc(ref, Faults(loss=0.05, seed=3))
    # every kind of message went missing about 5% of the time, each replaced by a guess ...
    per_kind = len(ref.t) * 6
    assert set(lossy.guessed) == {"A", "B", "C", "D"}
    assert all(0.03 * per_kind < n < 0.07 * per_kind for n in lossy.guessed.values()), lossy.guessed
    # ... and the arm kept on the path (the aims: <= 5 mm at 1 %, stable at 5 %)
    assert lossy.tool_error_mm_max <= 5.0
    late = track_vdc(ref, Faults(late_module=2, late_share=0.5, seed=3))
    assert set(late.guessed) == {"A", "C"} and late.tool_error_mm_max <= 5.0
    assert late.tool_error_mm_max > clean.tool_error_mm_max  # (a late module costs something)
    central = track_centralised(ref)
    assert central.tool_error_mm_max <= 2.0


@pytest.mark.slow
def test_cd_by_the_modules_with_this_cycles_neighbour_force_is_the_masters_bit_for_bit(ref) -> None:
    """[C, D] computed along the chain by the modules (each with its outboard neighbour's force of
    this cycle) is the master's backward recursion, redistributed: the same arm motion exactly.
    With the neighbour's force of the cycle before, it differs, and still tracks."""
    master = track_vdc(ref)
    chain = track_vdc(ref, where=(WHERE_NEIGHBOUR,) * 6)
    assert np.array_equal(master.q, chain.q)
    stale = track_vdc(ref, where=(WHERE_LOCAL,) * 6)
    assert not np.array_equal(master.q, stale.q) and stale.tool_error_mm_max <= 2.0


@pytest.mark.slow
def test_modules_that_misjudge_their_mass_adapt_it_and_track_again(ref) -> None:
    """Every module believes its body 40 % lighter than it is: without adaptation the arm sags off
    the path by millimetres; with VDC's parameter adaptation (each module its own, from its own
    body's velocities) the error falls to a fraction."""
    wrong = track_vdc(ref, believed=0.6)
    adapted = track_vdc(ref, gains=Gains(adapt=100.0), believed=0.6)
    assert wrong.tool_error_mm_max > 1.0
    assert adapted.tool_error_mm_max < wrong.tool_error_mm_max / 3
