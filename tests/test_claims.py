"""Claims only where the data determine them (magcal.diagnose.claims): a term the tests accept
is stated as a finding only when its size is plausible and the recording's halves agree on it;
otherwise it is a limit with its reason and the calibration is returned without it."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.core.series import Series
from magcal.diagnose import diagnose
from magcal.diagnose.locate.steps_scan import inflation
from magcal.sim.physics import Motion, Physics, Scenario

from test_diagnose import _sim

HARD = (21.0, -33.0, 8.0)


def _run(seed=5, n=5000):
    sc = Scenario(physics=Physics(hard_iron_ut=HARD, noise_ut=0.3), motion=Motion("sphere", period_s=20.0), seed=seed)
    return sc.simulate(n, 50.0).series


def _claims_limits(d):
    return [x for x in d.to_dict()["limits"] if x.get("check") == "claims"]


def test_a_true_modest_drift_is_a_finding():
    s = _run()
    m = s.field_ut + np.outer(s.t_s - s.t_s.mean(), (0.02, -0.015, 0.01))  # 2.7 µT over 100 s
    d = diagnose(Series(t_s=s.t_s, field_ut=m))
    assert "time_drift" in d.effects
    assert _claims_limits(d) == []


def test_an_implausibly_large_drift_is_a_limit_not_a_finding():
    s = _run()
    m = s.field_ut + np.outer(s.t_s - s.t_s.mean(), (0.3, -0.25, 0.1))  # 40 µT over 100 s
    d = diagnose(Series(t_s=s.t_s, field_ut=m))
    assert "time_drift" not in d.effects
    (limit,) = _claims_limits(d)
    assert limit["effect"] == "time_drift" and "more than 15% of the" in limit["summary"]
    assert "t_s" not in d.to_dict()["calibration"].get("coef_ut_per_unit", {})


def test_a_drift_only_in_the_first_half_is_not_claimed_as_a_drift():
    s = _run(seed=7)
    ramp = np.clip(s.t_s - s.t_s[0], 0, 50.0) - 25.0  # moves for 50 s, then holds
    m = s.field_ut + np.outer(ramp, (0.06, -0.05, 0.03))
    d = diagnose(Series(t_s=s.t_s, field_ut=m))
    assert "time_drift" not in d.effects
    (limit,) = _claims_limits(d)
    assert "halves" in limit["summary"] or "half" in limit["summary"]


def test_a_temperature_that_only_follows_what_a_refused_drift_leaves_is_not_credited():
    # the offset moves over the first half and then holds (no temperature in it); the logged
    # temperature is partly the bend a straight line leaves of that path. Beside the drift it
    # explains most of what is left and passes the wander gate; the drift's halves disagree and it
    # is refused — the temperature is then judged against the whole move as wander, and is no finding
    s = _run(seed=3, n=4000)
    tau = (s.t_s - s.t_s[0]) / np.ptp(s.t_s)
    rng = np.random.default_rng(3)
    v = rng.standard_normal(3)
    shape = np.minimum(tau, 0.5) * 2
    bent = shape - np.polyval(np.polyfit(tau, shape, 1), tau)
    other = np.sin(2 * np.pi * 1.3 * tau + rng.uniform(0, 6.28))
    x = 0.6 * bent / np.std(bent) + 0.4 * other / np.std(other)
    temp_c = 25 + 7.5 * x / np.max(np.abs(x))
    m = s.field_ut + np.outer(shape, 3.0 * v / np.linalg.norm(v))
    d = diagnose(Series(t_s=s.t_s, field_ut=m, channels={"temp_c": temp_c}))
    assert not [f for f in d.to_dict()["findings"] if (f.get("where") or {}).get("channel") == "temp_c"]
    assert "temperature_drift" not in d.effects
    (limit,) = _claims_limits(d)
    assert limit["effect"] == "time_drift" and "halves" in limit["summary"]
    (wander,) = [x for x in d.to_dict()["limits"] if x["effect"] == "offset_wander"]
    assert "temp_c" in wander["slow_term_floor_ut_per_unit"]


@pytest.mark.slow
def test_a_small_step_is_not_claimed_as_a_drift():
    # 0.6 µT put down at 40 % of the span: a straight line through it passes the halves, but
    # without it the offset's wander is one jump — the drift is a limit saying so, and the jump
    # is the remainder with its time
    run = _sim(142)
    t = run.series.t_s
    at_s = float(t[0] + 0.4 * np.ptp(t))
    d = diagnose(Series(t_s=t, field_ut=run.series.field_ut + np.outer(t >= at_s, [0.45, -0.3, 0.3])))
    assert "time_drift" not in d.effects
    (limit,) = _claims_limits(d)
    assert limit["effect"] == "time_drift" and "one jump" in limit["summary"]
    (rest,) = [x for x in d.to_dict()["limits"] if x["effect"] == "unexplained_structure"]
    assert abs(rest["where"]["time_s"][0] - at_s) <= 0.05 * np.ptp(t)


def test_the_correlation_inflation_is_one_on_white_noise_and_large_on_a_slow_wander():
    rng = np.random.default_rng(1)
    white = rng.standard_normal(4000)
    ones = np.ones((4000, 1))
    assert inflation(white, ones, 200) < 2.0
    slow = np.repeat(rng.standard_normal(8), 500) + 0.1 * white
    assert inflation(slow, ones, 200) > 20.0
