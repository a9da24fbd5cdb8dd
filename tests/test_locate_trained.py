"""A change point is judged on held-out blocks by a change those blocks did not help fit: its
own parameters (the step's vector, each side's ellipsoid) refitted on the training blocks alone.
Fitted on every sample, a side's ellipsoid on a short hand-held window fits the very block it is
scored on, and a change of shape looks better on "unseen" data that the recording contradicts."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magcal.diagnose.locate import EFFECTS, Kind, Located, as_limits, judge, steps
from magcal.sim.physics import Motion, Physics, Scenario

DATA = Path(__file__).parent / "data"
TABLE = {e.name: e for e in EFFECTS}


def _change(effect: str, tau_s: float, step_ut=(0.0, 0.0, 0.0)) -> Located:
    return Located(effect, Kind.PHYSICS, f"a change at {tau_s} s", {"time_s": [tau_s]},
                   {"time_s": tau_s, "step_ut": np.asarray(step_ut, float)}, {"size_ut": 1.0})


def test_a_shape_change_on_a_short_hand_held_window_is_not_kept_when_its_sides_are_fitted_without_the_block():
    """The third of four 14 s windows of the HMC5883L tilt take (a control: nothing was put
    near it) located a soft-iron change at 6.7 s; with each side's ellipsoid fitted on every
    sample it took held-out RMS 0.41 → 0.29 µT and was claimed. Fitted on the training blocks
    alone, each side's ellipsoid misses the block left out (→ 2.5 µT): the recording speaks
    against the change, so it is neither claimed nor left as unexplained structure."""
    a = np.loadtxt(DATA / "hmc5883l_sunsided_tilt_sphere_counts.csv", delimiter=",", skiprows=1)
    t, m = a[:, 0] - a[0, 0], a[:, 1:4] * 100.0 / 1090.0  # counts → µT (1090 LSB/G)
    edges = np.linspace(t[0], t[-1], 5)
    w = (t >= edges[2]) & (t < edges[3])
    change = _change(steps.SOFT, 6.68)
    _, (verdict,) = judge.judge(m[w], t[w] - t[w][0], {}, (change,), TABLE, "ellipsoid")
    assert not verdict.kept and verdict.contradicted, verdict.reason
    assert as_limits((change,), (verdict,)) == ()


def test_a_step_put_into_a_simulated_recording_is_still_kept():
    run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=Motion("sphere", period_s=10.0),
                   seed=5).simulate(1500, 50.0)
    t, m = run.series.t_s, run.series.field_ut
    d = np.array([1.0, -0.8, 0.6])
    _, (verdict,) = judge.judge(m + np.outer(t >= 15.0, d), t, {}, (_change(steps.STEP, 15.0, d),), TABLE, "ellipsoid")
    assert verdict.kept, verdict.reason
