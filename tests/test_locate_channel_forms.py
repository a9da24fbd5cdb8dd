"""Logged channels with lags, gains and nonlinear forms (magcal.diagnose.locate.channel_forms)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcal.diagnose.locate import Kind, Residual
from magcal.diagnose.locate import channel_forms as cf
from magcal.diagnose.locate.channel_terms import delayed, low_passed
from magcal.fit import fit_calibration
from magcal.sim.physics import Motion, Physics, Scenario

DATA = Path(__file__).parent / "data" / "lsm9ds1_ckexplorer_every4th.csv"
HARD = (12.0, -7.0, 4.0)


def _residual(m, t, chans) -> Residual:
    cal = fit_calibration(m, model="ellipsoid", outliers=False).calibration
    r = np.linalg.norm(cal.correct(m), axis=1) - cal.field_ut
    return Residual(t, m, cal, 0.4, float(np.sqrt(np.mean(r**2))), chans)


def _sim(seed, n=2000):
    sc = Scenario(physics=Physics(hard_iron_ut=HARD), motion=Motion("sphere", period_s=15.0), seed=seed)
    s = sc.simulate(n, 50.0).series
    return s.field_ut, s.t_s


def _temp(t, periods=1.6):
    return 22.5 + 7.5 * np.sin(2 * np.pi * periods * (t - t[0]) / np.ptp(t) + 0.4)


def _current(t, seed):
    rng = np.random.default_rng(seed)
    c, s = np.zeros(len(t)), t[0]
    while s < t[-1]:
        d = rng.uniform(1.0, 4.0)
        c[(t >= s) & (t < s + d)] = rng.uniform(1.0, 3.0) * (rng.random() < 0.5)
        s += d
    return c


def _servo(t, seed):
    rng = np.random.default_rng(seed)
    th, s = np.zeros(len(t)), t[0]
    while s < t[-1]:
        d = rng.uniform(1.5, 4.0)
        th[(t >= s) & (t < s + d)] = rng.uniform(-70, 70)
        s += d
    return th


def _only(found, effect):
    assert [f.effect for f in found] == [effect], [f.summary for f in found]
    assert found[0].kind is Kind.PHYSICS
    return found[0]


def test_current_through_a_first_order_lag_is_found_with_its_lag_and_coefficient():
    m, t = _sim(1)
    c = _current(t, 1)
    beta = np.array([0.3, -0.45, 0.2])  # µT/A
    f = _only(cf.search(_residual(m + np.outer(low_passed(c, t, 0.6), beta), t, {"current_a": c})), "lagged_channel")
    assert f.where["channel"] == "current_a"
    assert f.params["lag_kind"] == "first_order"
    assert abs(f.where["lag_s"] - 0.6) <= 0.3 * 0.6
    got = np.asarray(f.params["coef_ut_per_unit"])
    assert np.linalg.norm(got - beta) <= 0.2 * np.linalg.norm(beta)
    lo, hi = f.params["coef_magnitude_interval"]
    assert lo <= np.linalg.norm(beta) <= hi
    assert "first-order lag of" in f.summary and "µT/A" in f.summary


def test_a_current_delayed_by_the_logs_own_clock_is_said_as_a_delay_not_as_a_first_order_lag():
    # a first-order lag is what a current through the sensor's surroundings does; a pure delay must
    # fit clearly better to be said, and a true one does
    m, t = _sim(2)
    c = _current(t, 2)
    beta = np.array([-0.35, 0.25, 0.3])  # µT/A
    f = _only(cf.search(_residual(m + np.outer(delayed(c, t, 0.5), beta), t, {"current_a": c})), "lagged_channel")
    assert f.params["lag_kind"] == "delay"
    assert abs(f.where["lag_s"] - 0.5) <= 0.3 * 0.5
    assert np.linalg.norm(np.asarray(f.params["coef_ut_per_unit"]) - beta) <= 0.2 * np.linalg.norm(beta)


def test_a_first_order_lag_on_a_clock_that_comes_in_bursts_is_found_in_seconds():
    # samples in bursts (three 4 ms apart, then a 60 ms wait): the median interval is a quarter of
    # the mean, and a filter run at the median interval put the lag at about a quarter of 0.6 s
    m, _ = _sim(5)
    t = np.cumsum(np.tile([0.004, 0.004, 0.004, 0.060], len(m) // 4 + 1)[: len(m)])
    c = _current(t, 5)
    lagged, a = np.zeros(len(t)), np.exp(-np.diff(t, prepend=t[0]) / 0.6)
    for i in range(1, len(t)):  # the lag as the hardware has it, step by step in time
        lagged[i] = a[i] * lagged[i - 1] + (1 - a[i]) * c[i]
    beta = np.array([0.3, -0.45, 0.2])
    f = _only(cf.search(_residual(m + np.outer(lagged, beta), t, {"current_a": c})), "lagged_channel")
    assert abs(f.where["lag_s"] - 0.6) <= 0.3 * 0.6


def test_a_clock_coarser_than_the_samples_is_searched_not_refused():
    # a log's whole-second time column at 50 Hz: most intervals are 0, and the lag grid was built
    # from a median interval of 0 (a ValueError from diagnose on a real flight log's preflight take)
    m, t = _sim(3, n=1500)
    t_whole = np.floor(t)
    c = _temp(t)
    found = cf.search(_residual(m, t_whole, {"temp_c": c}))
    assert [f.effect for f in found if f.kind is Kind.PHYSICS] == []


def test_a_gain_that_follows_temperature_is_told_from_an_offset():
    m, t = _sim(2)
    temp = _temp(t)
    g = 0.004  # 0.4 %/°C
    mg = HARD + (m - HARD) * (1.0 + g * (temp - temp.mean()))[:, None]
    f = _only(cf.search(_residual(mg, t, {"temp_c": temp})), "temperature_gain")
    assert f.params["form"] == "gain"
    assert abs(f.params["gain_pct_per_unit"][0] - 100 * g) <= 0.3 * 100 * g
    assert "%/°C" in f.summary


def test_a_servo_arm_is_found_as_the_cosine_and_sine_of_its_angle():
    m, t = _sim(3)
    th = _servo(t, 3)
    v1, v2 = np.array([1.2, 0.3, -0.5]), np.array([-0.4, 0.9, 0.6])
    arm = np.outer(np.cos(np.deg2rad(th)), v1) + np.outer(np.sin(np.deg2rad(th)), v2)
    f = _only(cf.search(_residual(m + arm, t, {"servo_angle_deg": th})), "channel_angle")
    assert f.params["angle_unit"] == "deg"
    assert np.linalg.norm(np.asarray(f.params["sin_ut"]) - v2) <= 0.3 * np.linalg.norm(v2)


def test_a_clean_simulation_with_channels_claims_nothing():
    m, t = _sim(4)
    chans = {"temp_c": _temp(t), "current_a": _current(t, 4), "servo_angle_deg": _servo(t, 4)}
    assert cf.search(_residual(m, t, chans)) == ()


@pytest.fixture(scope="module")
def real():
    a = np.loadtxt(DATA, delimiter=",", skiprows=1)
    m = a[:, -3:]
    t = np.arange(len(m)) / 50.0
    return m, t


def test_a_temperature_offset_injected_into_a_real_recording_is_found_and_removed(real):
    m, t = real
    temp = _temp(t, 1.3)
    floor = _residual(m, t, {}).floor_ut
    beta = np.array([0.5, -0.3, 0.6])
    beta *= 6 * floor / (np.linalg.norm(beta) * 7.5)  # the largest offset 6× the recording's floor
    mm = m + np.outer(temp - temp.mean(), beta)
    res = _residual(mm, t, {"temp_c": temp})
    f = _only(cf.search(res), "temperature_drift")
    assert f.where["channel"] == "temp_c"
    assert abs(f.params["coef_magnitude_ut_per_unit"] - np.linalg.norm(beta)) <= 0.3 * np.linalg.norm(beta)
    cleaned = cf.remove(mm, t, {"temp_c": temp}, f)
    assert cf.search(_residual(cleaned, t, {"temp_c": temp})) == ()
    # the calibration refitted on the cleaned samples is the one at the reference (the end value)
    at_end = fit_calibration(m + np.outer(np.full(len(t), temp[-1]) - temp.mean(), beta), model="ellipsoid",
                             outliers=False).calibration.offset_ut
    refit = fit_calibration(cleaned, model="ellipsoid", outliers=False).calibration.offset_ut
    assert np.linalg.norm(refit - at_end) <= 0.3 * 6 * floor


def test_a_real_recording_with_synthetic_channels_claims_nothing(real):
    m, t = real
    chans = {"temp_c": _temp(t, 1.3), "current_a": _current(t, 7)}
    assert cf.search(_residual(m, t, chans)) == ()


def test_every_name_the_search_returns_has_a_row_with_its_model_and_only_the_first_searches():
    names = [e.name for e in cf.EFFECTS]
    assert names[0] == "lagged_channel" and {"temperature_gain", "channel_angle", "channel_step"} <= set(names)
    assert all(e.remove is cf.remove for e in cf.EFFECTS)
    assert all(e.search(None) == () for e in cf.EFFECTS[1:])


def test_tried_names_every_form_for_every_channel_and_remove_refuses_a_missing_channel():
    t = np.arange(100) / 10.0
    lines = cf.tried({"temp_c": np.linspace(20, 30, 100), "servo_angle_deg": np.sin(t), "flat": np.ones(100)})
    assert any(s.startswith("temp_c:") and "first-order" in s and "gain" in s and "step" in s for s in lines)
    assert any(s.startswith("servo_angle_deg:") and "cosine and sine" in s for s in lines)
    assert any(s.startswith("flat:") and "not tried" in s for s in lines)
    from magcal.diagnose.locate import Located

    loc = Located("lagged_channel", Kind.PHYSICS, "x", {"channel": "current_a"},
                  {"channel": "current_a", "form": "offset_delay", "reference": 0.0, "coef_ut_per_unit": [1, 0, 0]})
    with pytest.raises(ValueError, match="current_a"):
        cf.remove(np.zeros((100, 3)), t, {"temp_c": t}, loc)


SPHERE = Path(__file__).parent / "data" / "hmc5883l_sunsided_full_sphere_every3rd.csv"


def test_a_lagged_current_on_a_real_recording_gets_its_coefficient_and_lag_despite_its_wandering_residual():
    # the real residual is strongly autocorrelated (its block inflation ~50): fitted as if white,
    # this case's coefficient came out 23 % off (and 20–38 % on 7 of 10 such seeds); prewhitened, 7 %
    a = np.loadtxt(SPHERE, delimiter=",", skiprows=1)[::2]  # every 6th sample of the take
    t, m = a[:, 0], a[:, 1:4] * 100.0
    rng = np.random.default_rng(37)
    c = 8.0 * (np.sin(2 * np.pi * t / 9.0 + rng.uniform(0, 6)) > 0.2) + 0.2 * rng.standard_normal(len(t))
    beta = rng.standard_normal(3)
    beta *= 4 * _residual(m, t, {}).floor_ut / (8.0 * np.linalg.norm(beta))  # 4× the recording's floor at 8 A
    tau = rng.uniform(0.3, 1.0)
    f = _only(cf.search(_residual(m + np.outer(low_passed(c, t, tau), beta), t, {"current_a": c})), "lagged_channel")
    assert np.linalg.norm(np.asarray(f.params["coef_ut_per_unit"]) - beta) <= 0.2 * np.linalg.norm(beta)
    lo, hi = f.params["coef_magnitude_interval"]
    assert lo <= np.linalg.norm(beta) <= hi
    assert abs(f.where["lag_s"] - tau) <= 0.3 * tau
    lo, hi = f.params["lag_interval_s"]
    assert lo <= tau <= hi


def test_the_first_order_lag_on_an_uneven_clock_is_the_step_by_step_filter():
    rng = np.random.default_rng(0)
    t = np.cumsum(np.tile([0.004, 0.004, 0.004, 0.060], 500))
    t[50] = t[49]  # a repeated time
    c = np.cumsum(rng.standard_normal(len(t)))
    for tau in (0.0005, 0.05, 0.6, 40.0):
        y, a = np.empty_like(c), np.exp(-np.diff(t) / tau)
        y[0] = c[0]
        for i in range(1, len(t)):
            y[i] = a[i - 1] * y[i - 1] + (1 - a[i - 1]) * c[i]
        np.testing.assert_allclose(low_passed(c, t, tau), y, rtol=0, atol=1e-9 * np.max(np.abs(c)))


TILT = Path(__file__).parent / "data" / "hmc5883l_sunsided_tilt_sphere_counts.csv"


def test_a_periodic_current_the_calibration_carries_gets_its_lag_where_its_own_null_cannot_clear_it():
    # a 9 s square-wave current on a 56 s take: every circular shift of the channel, delayed by a
    # lag tried, lines the current up with its own effect again, so the shift null is learned from
    # the effect (this seed: nothing claimed on the channel's own evidence). The catalogue already
    # found the current's no-lag term; its form is still asked of the data.
    a = np.loadtxt(TILT, delimiter=",", skiprows=1)
    t, m = a[:, 0], a[:, 1:4]
    rng = np.random.default_rng(1)
    c = 8.0 * (np.sin(2 * np.pi * t / 9.0 + rng.uniform(0, 6)) > 0.2) + 0.2 * rng.standard_normal(len(t))
    beta = rng.standard_normal(3)
    beta *= 4 * _residual(m, t, {}).floor_ut / (8.0 * np.linalg.norm(beta))
    tau = rng.uniform(0.3, 1.0)

    def carried(mm):
        res = _residual(mm, t, {"current_a": c})
        cal = replace(res.calibration, coef_ut_per_unit={"current_a": beta}, reference={"current_a": 0.0})
        return Residual(t, mm, cal, res.noise_ut, res.floor_ut, {"current_a": c})

    f = _only(cf.search(carried(m + np.outer(low_passed(c, t, tau), beta))), "lagged_channel")
    assert f.params["lag_kind"] == "first_order"
    assert abs(f.where["lag_s"] - tau) <= 0.3 * tau
    assert np.linalg.norm(np.asarray(f.params["coef_ut_per_unit"]) - beta) <= 0.2 * np.linalg.norm(beta)
    # the same current with no lag is the calibration's own term: nothing is added beside it
    assert [x.effect for x in cf.search(carried(m + np.outer(c, beta)))] == []


def test_a_straight_temperature_term_beside_a_wander_is_not_named_a_curve():
    # the offset follows the temperature in a straight line (0.05 µT/°C, 1.5 cycles of ±7.5 °C)
    # on a sensor whose offset also wanders (0.15 µT, 8 s): the square of a slow channel is one
    # more slow curve, and this wander is followed by it better than by the square shifted in time
    # only by chance — no square law may be claimed
    from magcal.core.series import Series
    from magcal.diagnose import diagnose
    from magcal.sim.wander import WanderComponent

    seed = 7
    rng = np.random.default_rng(seed)
    phys = Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.2, wander=(WanderComponent(sigma_ut=0.15, tau_s=8.0),))
    run = Scenario(physics=phys, motion=Motion("sphere", period_s=20.0), seed=seed).simulate(3000, 50.0)
    t, m = run.series.t_s, run.series.field_ut
    temp_c = 22.5 + 7.5 * np.sin(2 * np.pi * 1.5 * (t - t[0]) / np.ptp(t) + rng.uniform(0, 6.28))
    k = rng.standard_normal(3)
    k *= 0.05 / np.linalg.norm(k)
    d = diagnose(Series(t_s=t, field_ut=m + np.outer(temp_c - temp_c.mean(), k), channels={"temp_c": temp_c}))
    assert "channel_square" not in d.effects
