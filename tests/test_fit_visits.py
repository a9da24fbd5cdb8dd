"""Visits: where residuals are correlated in time, a long rest in one pose counts as one visit."""

import numpy as np
import pytest

from magcal.fit import fit_calibration
from magcal.fit.direction_weights import direction_weights

VISIT_NOTE = "each visit to a direction cell weighted as one shared error"


def _direction(z, azimuth_deg):
    a = np.deg2rad(azimuth_deg)
    return 50.0 * np.array([np.sqrt(1 - z * z) * np.cos(a), np.sqrt(1 - z * z) * np.sin(a), z])


def _one_cell_then_another(long_run=400, short_runs=4, short_len=25):
    """Calibrated directions, each well inside one of the 32 cells: a long rest in one cell,
    then short passes through it between visits to another."""
    here, other = _direction(0.25, 22.5), _direction(-0.75, 202.5)
    parts, labels = [np.tile(here, (long_run, 1))], [np.zeros(long_run, int)]
    for i in range(short_runs):
        parts += [np.tile(other, (short_len, 1)), np.tile(here, (short_len, 1))]
        labels += [np.full(short_len, 1), np.full(short_len, 2 + i)]
    return np.concatenate(parts), np.concatenate(labels)


def test_without_correlation_the_balance_is_the_plain_one():
    h, _ = _one_cell_then_another()
    assert np.allclose(direction_weights(h, visit_correlation=0.0), direction_weights(h))


def test_a_long_rest_gives_weight_to_the_cells_other_visits_and_the_cell_keeps_its_share():
    h, run = _one_cell_then_another()
    plain, w = direction_weights(h), direction_weights(h, visit_correlation=0.05)
    here = run != 1
    assert np.isclose(w[here].sum(), plain[here].sum()) and np.isclose(w[~here].sum(), plain[~here].sum())
    rest, passes = w[run == 0], w[run >= 2]
    # per visit k/(1 + kρ): the 400-sample rest weighs 400/21 ≈ 19, each 25-sample pass 25/2.25 ≈ 11
    assert np.isclose(rest.sum() / w[run == 2].sum(), (400 / 21) / (25 / 2.25))
    assert rest.max() < plain[run == 0].min() and passes.min() > plain[run >= 2].max()


def _tumble_with_rest(seed, disturbance_ut=1.5, n=3000, rest=1200):
    """A hand tumble with, half way, a rest in one pose where the field is disturbed (the board
    put down beside something magnetic): radial error ``disturbance_ut`` on every rest sample."""
    rng = np.random.default_rng(seed)
    v, path = rng.normal(size=3), []
    for _ in range(n):
        v = v + 0.06 * rng.normal(size=3)
        v /= np.linalg.norm(v)
        path.append(v.copy())
    u = np.array(path)
    pose = u[n // 2]
    u = np.concatenate([u[: n // 2], pose + 0.01 * rng.normal(size=(rest, 3)), u[n // 2:]])
    u /= np.linalg.norm(u, axis=1)[:, None]
    soft = np.eye(3) + np.array([[0.04, 0.02, -0.01], [0.02, -0.03, 0.015], [-0.01, 0.015, 0.01]])
    offset_ut = np.array([12.0, -25.0, 8.0])
    m = (50.0 * u) @ soft.T + offset_ut + 0.3 * rng.normal(size=u.shape)
    m[n // 2: n // 2 + rest] += disturbance_ut * pose
    return m, np.r_[0 : n // 2, n // 2 + rest : n + rest]


@pytest.mark.parametrize("seed", [6, 8])
def test_a_disturbed_rest_counts_as_one_visit_and_pulls_the_offset_less(seed):
    m, moving = _tumble_with_rest(seed)
    r, without_rest = fit_calibration(m), fit_calibration(m[moving])
    assert VISIT_NOTE in r.reason
    # the plain balance lets the rest pull the offset 0.34 / 0.38 µT from the fit without it
    assert np.linalg.norm(r.calibration.offset_ut - without_rest.calibration.offset_ut) < 0.3


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_independent_noise_keeps_the_plain_balance(seed):
    m, _ = _tumble_with_rest(seed, disturbance_ut=0.0)
    r = fit_calibration(m)
    assert "direction cell counts equally" in r.reason and VISIT_NOTE not in r.reason
