"""A whole stream of the wander (magcal.sim.wander.draw_path) has the model's variance, band
power and correlation, on uniform sample times and on irregular ones alike."""

import numpy as np
import pytest

from magcal.sim import wander
from magcal.sim.wander import WanderComponent

BANDS = (WanderComponent(0.3, band_hz=(0.5, 2.0)), WanderComponent(0.2, band_hz=(10.0, 20.0), frame="field"))
DRAWS = 200


def _times(kind: str, n: int = 2000, dt: float = 0.02) -> np.ndarray:
    if kind == "uniform":
        return 5.0 + dt * np.arange(n)
    gaps = np.random.default_rng(5).choice([0.3 * dt, dt, 3.0 * dt], size=n - 1)  # bursts and gaps
    return np.concatenate([[5.0], 5.0 + np.cumsum(gaps)])


def _paths(components, t) -> np.ndarray:
    """(draws, n, 4): offset x, y, z and the field of independent draws."""
    out = []
    for k in range(DRAWS):
        off, fld = wander.draw_path(components, np.random.default_rng([k, 77]), t)
        out.append(np.column_stack([off, fld]))
    return np.array(out)


def _model_cov(components, lag_s: np.ndarray) -> np.ndarray:
    """(len(lag), 4) the model's covariance at the lags, per column."""
    out = np.zeros((len(lag_s), 4))
    for c in components:
        cols = [0, 1, 2] if c.frame == wander.OFFSET else [3]
        out[:, cols] += np.outer(c.correlation(lag_s), np.square(c.sigma_ut)[: len(cols)])
    return out


@pytest.mark.parametrize("kind", ["uniform", "irregular"])
def test_a_drawn_path_has_the_model_variance(kind):
    comps = BANDS + (WanderComponent(0.4, tau_s=0.5),)
    x = _paths(comps, _times(kind))
    var = x.var(axis=(0, 1))
    want = _model_cov(comps, np.zeros(1))[0]
    assert np.allclose(var, want, rtol=0.06), (var, want)


@pytest.mark.parametrize("kind", ["uniform", "irregular"])
def test_a_drawn_path_has_the_model_correlation_between_neighbours(kind):
    comps = BANDS + (WanderComponent(0.4, tau_s=0.05),)
    t = _times(kind)
    x = _paths(comps, t)
    for k in (1, 3, 10):
        emp = np.mean(x[:, k:] * x[:, :-k], axis=(0, 1))
        want = np.mean(_model_cov(comps, t[k:] - t[:-k]), axis=0)
        assert np.allclose(emp, want, atol=0.05 * _model_cov(comps, np.zeros(1))[0].max()), (k, emp, want)


def test_a_drawn_band_puts_its_power_inside_the_band_and_none_outside():
    dt = 0.02
    x = _paths(BANDS, _times("uniform", dt=dt))
    p = np.mean(np.abs(np.fft.rfft(x, axis=1)) ** 2, axis=0) / x.shape[1]  # (freqs, 4)
    f = np.fft.rfftfreq(x.shape[1], dt)
    for c, col in ((BANDS[0], 0), (BANDS[1], 3)):
        lo, hi = c.band_hz
        inside = (f > lo + 0.1 * (hi - lo)) & (f < hi - 0.1 * (hi - lo))
        level = c.sigma_ut[0] ** 2 / (2 * dt * (hi - lo))  # a flat band's periodogram level
        assert np.mean(p[inside, col]) == pytest.approx(level, rel=0.05)
        outside = (f < 0.5 * lo) | (f > 2.0 * hi)
        assert np.mean(p[outside, col]) < 0.01 * level
    assert np.mean(p[:, 0] * (f > 4.0)) < 1e-3 * np.mean(p[:, 0])  # the offset has no field band


def test_a_draw_is_a_function_of_the_generator_and_reads_each_time_in_order():
    t = _times("irregular", n=300)
    comps = BANDS + (WanderComponent(0.4, tau_s=0.5),)
    a = wander.draw_path(comps, np.random.default_rng(3), t)
    b = wander.draw_path(comps, np.random.default_rng(3), t)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert a[0].shape == (300, 3) and a[1].shape == (300,)
    one = wander.draw_path(comps, np.random.default_rng(3), t[:1])
    assert np.all(np.isfinite(one[0])) and one[0].shape == (1, 3)
    for kind in ("uniform", "irregular"):  # a field band alone leaves the offset untouched, and the reverse
        off, fld = wander.draw_path(BANDS[1:], np.random.default_rng(4), _times(kind, n=300))
        assert np.all(off == 0) and np.std(fld) > 0
        off, fld = wander.draw_path(BANDS[:1], np.random.default_rng(4), _times(kind, n=300))
        assert np.all(fld == 0) and np.all(np.std(off, axis=0) > 0)
