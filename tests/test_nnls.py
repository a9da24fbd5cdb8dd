"""Non-negative least squares (magcal.sim.nnls): the constrained optimum, as scipy's gives it."""

import numpy as np
import pytest
from scipy.optimize import nnls as scipy_nnls

from magcal.sim.nnls import nnls


def _problems(count=120):
    rng = np.random.default_rng(20261123)
    for k in range(count):
        n = int(rng.integers(1, 38))
        m = int(rng.integers(n, 60))
        a = rng.standard_normal((m, n)) * rng.random(n) ** 3 * 10.0 ** rng.integers(-3, 4)
        if k % 3 == 0:  # positive, nearly collinear columns, as spectra are
            a = np.abs(a) + 1e-3 * rng.random((m, n))
        b = rng.standard_normal(m) + (a @ np.abs(rng.standard_normal(n)) if k % 2 else 0.0)
        yield a, b * 10.0 ** rng.integers(-8, 9)


def test_the_solution_meets_the_optimality_conditions_and_scipys_residual():
    for a, b in _problems():
        x, rnorm = nnls(a, b)
        assert np.all(x >= 0)
        assert rnorm == pytest.approx(np.linalg.norm(a @ x - b), rel=1e-12, abs=1e-300)
        grad = a.T @ (a @ x - b) / np.linalg.norm(a, axis=0)  # per unit column
        scale = 1e-7 * np.linalg.norm(b)
        assert np.all(grad >= -scale)  # no column could lower the residual by growing
        assert np.all(np.abs(grad[x > 0]) <= scale)  # the free ones are at their optimum
        assert rnorm <= scipy_nnls(a, b)[1] * (1 + 1e-9) + 1e-9 * np.linalg.norm(b)


def test_a_right_hand_side_in_the_cone_is_met_exactly_and_a_zero_design_gives_zero():
    a = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    x, rnorm = nnls(a, a @ np.array([0.5, 3.0]))
    assert np.allclose(x, [0.5, 3.0]) and rnorm < 1e-12
    x, rnorm = nnls(a, -a @ np.array([0.5, 3.0]))
    assert np.array_equal(x, [0.0, 0.0])
    x, _ = nnls(np.zeros((4, 2)), np.ones(4))
    assert np.array_equal(x, [0.0, 0.0])


def test_a_start_from_a_nearby_problems_columns_gives_the_same_optimum():
    rng = np.random.default_rng(7)
    for a, b in _problems(60):
        cold, rnorm = nnls(a, b)
        near = nnls(a * (1.0 + 0.05 * rng.random(a.shape[1])), b * (1.0 + 0.05 * rng.random(len(b))))[0] > 0
        for start in (cold > 0, near, rng.random(a.shape[1]) < 0.5, np.ones(a.shape[1], bool)):
            x, r = nnls(a, b, start=start)
            np.testing.assert_allclose(x, cold, rtol=1e-9, atol=1e-9 * np.abs(cold).max(initial=1e-300))
            assert r == pytest.approx(rnorm, rel=1e-9, abs=1e-300)
