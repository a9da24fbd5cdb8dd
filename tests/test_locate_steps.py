"""Change points in time (magcal.diagnose.locate.steps): a hard-iron step found with its time
and vector, a soft-iron change with its gains, a misbehaving stretch as the remainder, and no
claim on a clean simulation, a slow wander, or a real recording without an injected change."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.diagnose.locate import steps
from magcal.diagnose.locate import steps_scan as scan
from magcal.diagnose.locate.base import REST, Kind, Residual
from magcal.fit import fit_calibration
from magcal.sim.physics import Motion, Physics, Scenario

DATA = Path(__file__).parent / "data"


def _sim(seed):
    run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=Motion("sphere", period_s=20.0),
                   seed=seed).simulate(4000, 50.0)
    return run.series.t_s, run.series.field_ut


def _search(t, m):
    fit = fit_calibration(m, model="ellipsoid")
    return steps.search(Residual(t, m, fit.calibration, 0.3, float(fit.rms_ut)))


def _floor(m):
    return float(fit_calibration(m, model="ellipsoid").rms_ut)


def _claims(found):
    return [f for f in found if f.kind is Kind.PHYSICS]


def test_a_step_is_found_with_its_time_and_vector_and_removed_to_the_end_calibration():
    t, m = _sim(1)
    d = np.array([1.0, 0.49, -0.59])
    d *= 4 * _floor(m) / np.linalg.norm(d)
    m2 = m + np.outer(t >= 37.09, d)
    found = _claims(_search(t, m2))
    assert [f.effect for f in found] == [steps.STEP], [f.summary for f in found]
    step = found[0]
    assert abs(step.where["time_s"][0] - 37.09) <= 1.0
    assert np.linalg.norm(step.params["step_ut"] - d) < 0.25 * np.linalg.norm(d)
    assert "µT at 37." in step.summary
    cleaned = steps.remove_step(m2, t, {}, step)
    refit = fit_calibration(cleaned, model="ellipsoid").calibration.offset_ut
    end = fit_calibration(m2[t >= 37.09], model="ellipsoid").calibration.offset_ut
    assert np.linalg.norm(refit - end) < 0.3 * np.linalg.norm(d)


def test_the_scan_of_every_candidate_at_once_agrees_with_a_regression_on_each_window():
    rng = np.random.default_rng(3)
    t = np.arange(1500) / 50.0
    u = rng.standard_normal((1500, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 0.3 * rng.standard_normal(1500) + (t >= 14.0) * (u @ [0.2, -0.1, 0.05])
    taus, half = np.array([8.0, 14.0, 20.3]), 4.0
    lo, k, hi = np.searchsorted(t, taus - half), np.searchsorted(t, taus), np.searchsorted(t, taus + half, "right")
    rss0, rss1 = scan.Moments(u, t, r, half).rss(lo, k, hi, taus)
    for i, tau in enumerate(taus):
        w = scan.window(t, tau, half)
        gain, fit = scan.step_gain(u[w], t[w], r[w], tau, half)
        assert rss1[i] == pytest.approx(fit.rss, rel=1e-8) and rss0[i] - rss1[i] == pytest.approx(gain, rel=1e-6)


def test_a_step_injected_into_a_real_recording_is_found_where_it_was_put():
    s = load_series(DATA / "lsm9ds1_ckexplorer_every4th.csv")
    t, m = np.asarray(s.t_s, float), np.asarray(s.field_ut, float)
    d = np.array([0.72, -0.9, 0.15])  # 3× the recording's floor
    found = [f for f in _claims(_search(t, m + np.outer(t >= 1649.4, d))) if abs(f.where["time_s"][0] - 1649.4) <= 0.05 * 2999]
    assert [f.effect for f in found] == [steps.STEP]
    assert np.linalg.norm(found[0].params["step_ut"] - d) < 0.5 * np.linalg.norm(d)


@pytest.mark.parametrize("shape", ["none", "ramp", "smooth"])
def test_no_step_on_a_clean_simulation_nor_on_a_slow_wander(shape):
    t, m = _sim(2)
    d = np.array([1.0, -2.0, 0.5])
    d *= 10 * _floor(m) / np.linalg.norm(d)
    drift = {"none": 0.0 * t, "ramp": (t - t[0]) / (t[-1] - t[0]), "smooth": np.sin(2 * np.pi * t / 60.0)}[shape]
    assert _claims(_search(t, m + np.outer(drift, d))) == []


def test_nothing_is_claimed_on_a_real_recording_without_a_change():
    s = load_series(DATA / "qmc5883l_tomisuarez_every5th_counts.csv")
    assert _claims(_search(np.asarray(s.t_s, float), np.asarray(s.field_ut, float))) == []


def test_a_soft_iron_change_is_timed_with_its_gain_and_removed_to_the_end_calibration():
    t, m = _sim(2)
    b = fit_calibration(m, model="sphere").calibration.offset_ut
    m3 = m.copy()
    after = t >= 45.0
    m3[after, 1] = b[1] + 1.025 * (m[after, 1] - b[1])
    found = _claims(_search(t, m3))
    assert [f.effect for f in found] == [steps.SOFT], [f.summary for f in found]
    soft = found[0]
    assert abs(soft.where["time_s"][0] - 45.0) <= 1.0 and soft.where["axis"] == "y"
    assert abs(soft.params["gain_change"][1] - 0.025) < 0.005
    refit = fit_calibration(steps.remove_soft(m3, t, {}, soft), model="ellipsoid").calibration
    end = fit_calibration(m3[after], model="ellipsoid").calibration
    assert np.allclose(refit.soft_iron, end.soft_iron, atol=2e-3)


def test_a_misbehaving_stretch_is_the_remainder_located_in_time():
    t, m = _sim(1)
    burst = m.copy()
    sel = (t > 30) & (t < 34)
    burst[sel] += np.random.default_rng(1).standard_normal((sel.sum(), 3)) * 5 * _floor(m)
    found = _search(t, burst)
    assert _claims(found) == []
    rest = [f for f in found if f.effect == REST]
    assert len(rest) == 1 and rest[0].kind is Kind.REMAINDER
    t0, t1 = rest[0].where["time_s"][0]
    assert abs(t0 - 30) <= 1.0 and abs(t1 - 34) <= 1.0 and "× the noise" in rest[0].summary


def test_bad_times_are_refused_with_a_clear_error():
    t, m = _sim(1)
    fit = fit_calibration(m, model="ellipsoid")
    with pytest.raises(ValueError, match="t_s"):
        steps.search(Residual(t[::-1].copy(), m, fit.calibration, 0.3, float(fit.rms_ut)))


def _tilt(seed):
    run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=Motion("tilt", max_tilt_deg=50.0),
                   seed=seed).simulate(4000, 50.0)
    return run.series.t_s, run.series.field_ut


def test_on_a_tilt_take_a_gain_change_is_named_a_soft_iron_change_and_a_step_a_step():
    # Under a tilt motion the direction is nearly a function of time, so a one-axis gain change
    # seen through the local offset model is a step there too; told at its time, the change of
    # shape adds beyond the step far more than the step adds beyond the change of shape.
    t, m = _tilt(8)
    size_ut = 4 * _floor(m)
    b = fit_calibration(m, model="sphere").calibration.offset_ut
    after = t >= 44.0
    soft = m.copy()
    soft[after, 0] = b[0] + (1 + size_ut / 50.0) * (m[after, 0] - b[0])
    found = _claims(_search(t, soft))
    assert [f.effect for f in found] == [steps.SOFT], [f.summary for f in found]
    assert abs(found[0].where["time_s"][0] - 44.0) <= 1.0 and found[0].where["axis"] == "x"
    d = np.array([0.6, -0.7, 0.4])
    found = _claims(_search(t, m + np.outer(after, 10 * _floor(m) * d / np.linalg.norm(d))))
    assert [f.effect for f in found] == [steps.STEP], [f.summary for f in found]
    assert abs(found[0].where["time_s"][0] - 44.0) <= 1.0
