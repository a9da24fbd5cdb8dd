"""The one home of tail probabilities (magcal.fit.tails): what each test in magcal asks of it,
at the points it asks, against scipy.stats and against what the callers were given before."""

import numpy as np
import pytest
from scipy import stats

from magcal.fit import tails
from magcal.fit.outliers import grubbs_critical

DFS = (1, 2, 3, 4.5, 7, 12, 30, 97.3, 500, 5000, 300000)


def test_t_quantiles_over_the_range_the_grubbs_test_uses():
    for df in DFS:
        for q in (0.975, 0.4, 0.05, 1e-3, 1e-6, 1e-9, 1e-12):
            assert tails.t_isf(q, df) == pytest.approx(stats.t.isf(q, df), rel=1e-12), (df, q)
            assert tails.t_sf(tails.t_isf(q, df), df) == pytest.approx(q, rel=1e-9), (df, q)


def test_grubbs_critical_values_are_what_the_fit_used_before():
    # the former Newton-on-continued-fraction quantile gave these (two-sided, α = 0.01)
    before = {3: 1.15468471, 10: 2.48208325, 100: 3.75400437, 10000: 4.88883525, 250000: 5.49069170}
    for n, g in before.items():
        assert grubbs_critical(n, 0.01) == pytest.approx(g, rel=1e-8), n


def test_chi2_tails_and_quantiles():
    for df in (1, 2, 3, 6, 30, 97.3):
        for x in (0.0, 0.3, 3.0, 11.3, 40.0, 300.0):
            assert tails.chi2_sf(x, df) == pytest.approx(stats.chi2.sf(x, df), rel=1e-12, abs=1e-300)
        for q in (0.5, 0.01, 1e-6, 1e-12):
            assert tails.chi2_isf(q, df) == pytest.approx(stats.chi2.isf(q, df), rel=1e-10)
    # the hard-iron comparison's closed form for 3 degrees of freedom, which it used before
    x = np.array([0.5, 7.8, 40.0])
    closed = [0.91889141165, 0.05033109786, 1.0655090334e-08]
    assert tails.chi2_sf(x, 3) == pytest.approx(closed, rel=1e-10)
    assert tails.chi2_sf(-1.0, 3) == 1.0


def test_f_tails_and_quantiles_keep_a_small_tails_digits():
    for dfn in (1, 2, 3, 9):
        for dfd in DFS[:-1]:
            for x in (0.0, 0.3, 2.5, 25.0):
                assert tails.f_sf(x, dfn, dfd) == pytest.approx(stats.f.sf(x, dfn, dfd), rel=1e-12, abs=1e-300)
            for q in (0.5, 0.05, 1e-4, 1e-8):
                x = tails.f_isf(q, dfn, dfd)
                assert x == pytest.approx(stats.f.isf(q, dfn, dfd), rel=1e-6)
                assert tails.f_sf(x, dfn, dfd) == pytest.approx(q, rel=1e-9), (q, dfn, dfd)


def test_a_probability_or_degrees_of_freedom_out_of_range_is_refused():
    with pytest.raises(ValueError, match="tail probability"):
        tails.t_isf(0.0, 5)
    with pytest.raises(ValueError, match="tail probability"):
        tails.chi2_isf(1.5, 3)
    with pytest.raises(ValueError, match="degrees of freedom"):
        tails.f_sf(2.0, 0, 10)


def test_chi2_log10_sf_agrees_with_scipy_and_stays_finite_where_the_tail_underflows():
    from scipy import stats

    x = np.array([0.5, 5.0, 50.0, 500.0])
    for df in (1, 3, 6):
        want = -stats.chi2.logsf(x, df) / np.log(10.0)
        assert np.allclose(tails.chi2_log10_sf(x, df), want, rtol=1e-9)
    far = tails.chi2_log10_sf(np.array([1300.0, 5000.0, 1e5]), 3)
    assert np.all(np.isfinite(far)) and np.all(np.diff(far) > 0)
    # the asymptotic branch continues the exact one: at x = 1300 (past the switch, still in range)
    assert abs(far[0] - (-stats.chi2.logsf(1300.0, 3) / np.log(10.0))) < 0.01
