"""The honest remainder (``unexplained_structure``) is sized against the recording's own noise
and slow wander: structure no larger than what the recording keeps without it is its noise and
the ``offset_wander`` limit's to state, not a second, vaguer statement of the same thing — and
both are measured with the structure taken out, so an effect never hides behind itself."""

from __future__ import annotations

import numpy as np

from magcal.diagnose.locate import Kind, Located, as_limits, judge, steps
from magcal.diagnose.locate.judge import Verdict
from magcal.sim.physics import Motion, Physics, Scenario

STEP = Located("hard_iron_step", Kind.PHYSICS, "a hard-iron step of (1, 0, 0) µT at 3.0 s", {"time_s": [3.0]})


def test_a_located_effect_whose_heldout_gain_is_within_the_noise_and_wander_left_without_it_is_no_remainder():
    # modelling it took sqrt(0.50² − 0.45²) = 0.22 µT RMS off unseen blocks
    small = Verdict(STEP, False, 0.50, 0.45, "not better beyond chance", wander_ut=0.10, noise_ut=0.12)
    large = Verdict(STEP, False, 0.50, 0.45, "not better beyond chance", wander_ut=0.15, noise_ut=0.18)
    (limit,) = as_limits((STEP,), (small,))
    assert limit["effect"] == "unexplained_structure" and limit["resembles"] == "hard_iron_step"
    assert as_limits((STEP,), (large,)) == ()
    assert large.evidence()["wander_without_ut"] == 0.15


def test_an_undetermined_shape_change_stays_the_remainder_with_its_size_against_noise_and_wander():
    """Its wander still holds part of the change, so it is not sized away; the figures are said."""
    change = steps.ShapeChange(20.0, (19.0, 21.0), np.full(6, 0.5), np.ones(6), 27.0, 25.7, (False, True),
                               explained_ut=0.04, allowed_ut=0.05)
    found = steps._soft_located(change, 0.2, 50.0)
    assert found.effect == "unexplained_structure" and found.kind is Kind.REMAINDER
    assert found.evidence["explained_ut"] == 0.04 and found.evidence["noise_and_wander_without_ut"] == 0.05


def test_the_wander_that_sizes_a_remainder_is_measured_with_the_effect_taken_out():
    """A step left in the samples shows as wander; taken out, the recording's own is left."""
    run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=Motion("sphere", period_s=20.0),
                   seed=5).simulate(1500, 50.0)
    t, m = run.series.t_s, run.series.field_ut
    with_step = m + np.outer(t >= 15.0, [2.0, -1.5, 1.0])
    noise, wander = judge.without_it(m, "ellipsoid")
    assert abs(noise - 0.3) < 0.05
    assert judge.without_it(with_step, "ellipsoid")[1] > 3 * wander


def test_a_soft_iron_change_must_beat_the_offset_alone_changing_at_its_time():
    """An offset step dressed as a soft-iron change: held-out blocks prefer it to nothing, but
    not to the offset changing alone at the same time, so no soft-iron change is claimed."""
    from magcal.diagnose.locate import EFFECTS

    run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=Motion("sphere", period_s=20.0),
                   seed=5).simulate(1500, 50.0)
    t, m = run.series.t_s, run.series.field_ut
    stepped = m + np.outer(t >= 15.0, [2.0, -1.5, 1.0])
    soft = Located("soft_iron_change", Kind.PHYSICS, "the soft iron changed at 15.0 s", {"time_s": [15.0]},
                   {"time_s": 15.0})
    _, (verdict,) = judge.judge(stepped, t, {}, (soft,), {e.name: e for e in EFFECTS}, "ellipsoid")
    assert not verdict.kept and "simpler account" in verdict.reason
