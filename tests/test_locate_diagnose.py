"""The locate step inside `diagnose`: what a user reads when the recording holds physics the
catalogue has no term for — where it is, what it is, and the calibration in force at the end."""

from __future__ import annotations

import numpy as np

from magcal.core.series import Series
from magcal.diagnose import diagnose
from magcal.diagnose.locate import Kind, Located, as_limits
from magcal.diagnose.locate.judge import Verdict
from magcal.sim.physics import Motion, Physics, Scenario

HARD = (21.0, -33.0, 8.0)
STEP = np.array([2.4, -2.0, 1.6])  # 3.5 µT, about 10× this recording's floor


def _run(seed=11, n=4000, rate_hz=50.0):
    sc = Scenario(physics=Physics(hard_iron_ut=HARD, noise_ut=0.3), motion=Motion("sphere", period_s=20.0), seed=seed)
    return sc.simulate(n, rate_hz).series


def _located(d, effect):
    return [f for f in d.to_dict()["findings"] if f["effect"] == effect]


def test_a_hard_iron_step_is_found_where_it_happened_and_the_end_calibration_returned():
    s = _run()
    m = s.field_ut + np.outer(s.t_s >= 47.3, STEP)
    d = diagnose(Series(t_s=s.t_s, field_ut=m))
    (step,) = _located(d, "hard_iron_step")
    (tau,) = np.ravel(step["where"]["time_s"])[:1]
    assert abs(tau - 47.3) <= 1.0
    assert step["evidence"]["modelled"] is True
    assert np.allclose(d.to_dict()["calibration"]["offset_ut"], np.add(HARD, STEP), atol=0.4)
    assert "time_drift" not in d.effects


def test_mains_hum_aliased_by_the_sample_clock_is_a_line_at_its_frequency():
    s = _run(rate_hz=47.6)
    hum = np.zeros_like(s.field_ut)
    hum[:, 1] = 1.2 * np.cos(2 * np.pi * 50.0 * s.t_s)  # seen at 50 − 47.6 = 2.4 Hz
    d = diagnose(Series(t_s=s.t_s, field_ut=s.field_ut + hum))
    (line,) = _located(d, "narrowband_line")
    assert abs(float(np.ravel(line["where"]["frequency_hz"])[0]) - 2.4) < 0.02 * 2.4
    assert "50 Hz" in line["summary"]


def test_a_clean_recording_locates_nothing():
    d = diagnose(_run(seed=12))
    kinds = {f.get("evidence", {}).get("kind") for f in d.to_dict()["findings"]}
    assert not kinds & {"physics", "fault"}
    assert not [x for x in d.to_dict()["limits"] if x["effect"] == "unexplained_structure"]


def _verdict(loc, without, with_, kept=False):
    return Verdict(loc, kept, without, with_, "held-out RMS")


def test_a_located_effect_that_is_not_modelled_is_the_remainder_and_one_unseen_data_contradict_is_not_said():
    loc = Located("hard_iron_step", Kind.PHYSICS, "a hard-iron step of (1, 0, 0) µT at 3.0 s", {"time_s": [3.0]})
    (limit,) = as_limits((loc,), (_verdict(loc, 0.50, 0.49),))
    assert limit.effect == "unexplained_structure" and limit.details["resembles"] == "hard_iron_step"
    assert limit.to_dict()["where"] == {"time_s": [3.0]}
    assert as_limits((loc,), (_verdict(loc, 0.50, 0.55),)) == ()


def test_the_report_draws_the_samples_as_the_returned_calibration_takes_them(tmp_path):
    """With a step modelled, the page's calibrated samples are the ones the step was taken out
    of: their RMS is the final RMS the terminal and the JSON state, not the step's spread."""
    from magcal.app.report.views import views_of

    s = _run()
    m = s.field_ut + np.outer(s.t_s >= 47.3, STEP)
    d = diagnose(Series(t_s=s.t_s, field_ut=m))
    v = views_of(d)
    assert np.sqrt(np.mean(v.after[v.good] ** 2)) < 1.2 * d.final.rms_ut
    assert abs(d.final_heldout_rms_ut - d.to_dict()["final"]["heldout_rms_ut"]) < 1e-12
    assert not [x for x in d.to_dict()["limits"] if x["effect"] == "offset_wander"]


def test_a_lagged_current_is_one_finding_on_its_channel_in_place_of_the_no_lag_term():
    """The channel test finds a current through a 0.4 s lag as a plain no-lag offset and the
    locate step finds its lag: the user reads one finding on current_a — the lagged one, with its
    lag — and the calibration carries no no-lag current term beside it."""
    from magcal.diagnose.locate.channel_terms import low_passed
    from magcal.sim.physics import Current

    sc = Scenario(physics=Physics(hard_iron_ut=HARD, noise_ut=0.3), motion=Motion("sphere", period_s=20.0),
                  current=Current(level_a=4.0, segment_s=4.0), seed=21)
    s = sc.simulate(3000, 50.0).series
    beta = np.array([0.75, -0.6, 0.45])  # µT/A: up to 4.2 µT at 4 A
    cur = s.channels["current_a"]
    d = diagnose(Series(t_s=s.t_s, field_ut=s.field_ut + np.outer(low_passed(cur, s.t_s, 0.4), beta),
                        channels={"current_a": cur})).to_dict()
    on = [f for f in d["findings"] if f["where"].get("channel") == "current_a"]
    assert [f["effect"] for f in on] == ["lagged_channel"], [f["effect"] for f in d["findings"]]
    assert abs(on[0]["where"]["lag_s"] - 0.4) <= 0.3 * 0.4
    assert np.linalg.norm(np.asarray(on[0]["params"]["coef_ut_per_unit"]) - beta) <= 0.2 * np.linalg.norm(beta)
    assert on[0]["evidence"]["replaces"]["effect"] == "current_interference"
    assert "current_a" not in d["calibration"].get("coef_ut_per_unit", {})
