"""Fitting the wander's spectrum (magcal.sim.wander.fit) and the noise beside it: a recording's
white floor and its bands, as a twin must reproduce them."""

import numpy as np
import pytest

from magcal.core.calibration import Calibration
from magcal.core.series import Series
from magcal.diagnose import twin
from magcal.fit import fit_calibration as fit
from magcal.sim import wander
from magcal.sim.model import SensorModel
from magcal.sim.physics import Motion, Physics, Scenario
from magcal.sim.wander import FIELD, WanderComponent


def _field_series(components, t, white_ut, seed=5):
    rng = np.random.default_rng(seed)
    _, f = wander.draw_path(components, rng, t)
    return f + white_ut * rng.standard_normal(len(t))


def _directions(n, seed=6):
    u = np.random.default_rng(seed).standard_normal((n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def test_the_white_floor_is_found_on_irregularly_sampled_times():
    """~425 Hz with gaps, as a logger that drops and bunches samples gives: the band
    frequencies no longer line up with the periodogram's, yet the white noise is the level
    the spectrum never falls below."""
    rng = np.random.default_rng(1)
    dt = np.where(rng.random(20000) < 0.03, rng.uniform(0.02, 0.07, 20000), rng.uniform(0.0019, 0.0027, 20000))
    t = np.cumsum(dt)
    e = _field_series((WanderComponent(0.05, band_hz=(0.01, 0.05), frame=FIELD),), t, 0.2)
    comps, white = wander.fit(e, _directions(len(t)), t)
    assert 0.8 < white / 0.2**2 < 1.2
    assert sum(c.variance for c in comps) < 0.5 * white


def test_a_weak_band_above_a_steep_red_end_is_kept():
    """Most of the variance in a slow band, a little at 0.5–1 Hz: the little sets how smooth
    the reading is from second to second, and is kept though it is far below 1 % of the
    total."""
    t = np.arange(15000) / 50.0
    truth = (WanderComponent(3.0, band_hz=(0.004, 0.01), frame=FIELD), WanderComponent(0.15, band_hz=(0.5, 1.0), frame=FIELD))
    e = _field_series(truth, t, 0.02)
    comps, white = wander.fit(e, _directions(len(t)), t, frames=(FIELD,))
    mid = sum(c.variance * max(0.0, min(c.band_hz[1], 1.2) - max(c.band_hz[0], 0.4)) / (c.band_hz[1] - c.band_hz[0])
              for c in comps)
    assert 0.5 < mid / 0.15**2 < 2.0


@pytest.mark.slow
def test_the_noise_learned_through_a_strong_soft_iron_is_the_sensors_own():
    """Noise enters the raw reading ahead of the soft iron: learned through the field
    direction alone, a sensor whose soft iron stretches one axis by 1.45 and shrinks another by
    0.69 got its noise 6 % too large (the radial residual sees Wᵀu·noise)."""
    cal = Calibration(offset_ut=[5.0, -8.0, 12.0], field_ut=40.0,
                      soft_iron=[[1.45, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.69]])
    truth = SensorModel(calibration=cal, noise_ut=(0.3, 0.3, 0.3))
    sc = Scenario(physics=Physics(), motion=Motion("sphere", period_s=15.0), seed=4, model=truth)
    series = sc.simulate(8000).series
    learned = twin.learn(series, fit(series.field_ut, model="ellipsoid").calibration)
    assert abs(np.mean(learned.noise_ut) / 0.3 - 1.0) < 0.05  # through u alone: 0.317 (+6 %)


def _arrival_stamps(n, rate_hz, seed=8):
    """Host arrival times of a sensor sampling at ``rate_hz``: read out in bursts every
    0.1–0.25 s, each burst's samples stamped 2 ms apart (as a serial host sees an HMC5883L)."""
    rng = np.random.default_rng(seed)
    true = np.arange(n) / rate_hz
    reads = np.cumsum(rng.uniform(0.1, 0.25, int(true[-1] / 0.1) + 2))
    burst = np.searchsorted(reads, true)  # the read that fetches each sample
    first = np.searchsorted(burst, burst)  # index of the first sample in the same burst
    return reads[burst] + 0.002 * (np.arange(n) - first)


def test_bursty_stamps_of_a_regular_sensor_give_its_own_band_top():
    """A 77 Hz sensor stamped on arrival (bursts 2 ms apart, gaps up to 250 ms; median interval
    2 ms) has the sample rate it has stamped regularly: the wander's bands end at the same top,
    the sensor's 38.5 Hz Nyquist frequency (from the median interval they reached 250 Hz), no
    learned band lies above it, and the twin is a 77 Hz sensor."""
    rate, n = 77.0, 4000
    truth = SensorModel(calibration=Calibration(offset_ut=[5.0, -8.0, 12.0], field_ut=40.0), noise_ut=(0.1,) * 3,
                        wander=(WanderComponent(0.3, band_hz=(0.05, 0.5)),))
    series = Scenario(physics=Physics(), motion=Motion("sphere", period_s=15.0), seed=4, model=truth).simulate(n, rate).series
    bursty = _arrival_stamps(n, rate)
    assert np.median(np.diff(bursty)) < 0.0025 and np.all(np.diff(bursty) > 0)
    cal = fit(series.field_ut, model="ellipsoid").calibration
    tops = []
    for t in (series.t_s, bursty):
        tops.append(wander.band_edges(wander.sample_interval(t), float(t[-1] - t[0]))[-1])
        learned = twin.learn(Series(t_s=t, field_ut=series.field_ut), cal)
        assert learned.rate_hz == pytest.approx(rate, rel=0.02)
        assert all(c.band_hz[1] <= tops[-1] * (1 + 1e-9) for c in learned.wander if c.band_hz)
    assert tops[0] == pytest.approx(rate / 2, rel=1e-6)
    assert tops[1] == pytest.approx(tops[0], rel=0.02)


def test_a_residual_without_power_has_no_wander_and_no_noise():
    """A residual that is exactly constant (a fit that leaves nothing, as readings scaled far
    out of range can) is a sensor without wander or noise — it raised ValueError in the
    Whittle fit's empty solve, so `diagnose --twin` stopped with a traceback."""
    t = np.arange(200) * 0.02
    assert wander.fit(np.zeros(200), _directions(200), t) == ((), 0.0)


def test_a_wander_slower_than_the_fit_can_see_is_continued_flat_below_it():
    """A flat field wander from 0.0025 to 0.2 Hz on 200 s, the residual seen after a level and
    a straight line in time are fitted out (a time drift among the candidates): the lowest bands
    are nearly all taken by the line and cannot be fitted. Dropped, the twin would never draw a
    trend, and every such trend would pass for a drift; with ``flat_below`` they are drawn at
    the lowest fitted band's density, here the wander's own."""
    t = np.arange(2000) / 10.0
    density = 0.5**2 / (0.2 - 0.0025)
    truth = (WanderComponent(0.5, band_hz=(0.0025, 0.2), frame=FIELD),)
    e = _field_series(truth, t, 0.05, seed=8)
    x = np.column_stack([np.ones_like(t), t - t.mean()])

    def project(v):
        return v - x @ np.linalg.lstsq(x, v, rcond=None)[0]

    u = _directions(len(t))
    seen, _ = wander.fit(project(e), u, t, project, frames=(FIELD,))
    continued, _ = wander.fit(project(e), u, t, project, frames=(FIELD,), flat_below=True)
    lowest = min(c.band_hz[0] for c in seen)
    assert lowest > 0.004  # the line takes the lowest band
    below = [c for c in continued if c.band_hz[1] <= lowest * (1 + 1e-9)]
    assert below and min(c.band_hz[0] for c in below) == pytest.approx(0.0025, rel=0.01)
    for c in below:
        assert 0.3 < c.variance / (c.band_hz[1] - c.band_hz[0]) / density < 3.0
    assert set(seen) <= set(continued)
