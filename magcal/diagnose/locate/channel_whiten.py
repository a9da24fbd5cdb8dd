"""A lagged channel's lag and coefficient from the prewhitened residual (generalised least squares).

The radial residual of a real recording is strongly autocorrelated: slow wander and the
calibration's own misfit along the trajectory (the block covariance's inflation reaches 40–60
on the hmc5883l and betaflight logs). An ordinary least-squares fit of β·c(t) against it is
unbiased but weighs that slow structure as if it were white, so the part of it that happens to
line up with the channel × orientation pulls the coefficient's *direction* 20–45 % off and the
lag with it, and its interval says so only through a large inflation.

Here the residual's own autoregressive filter (Yule–Walker, order by AIC up to ``MAX_ORDER``),
learned from the residual with the located term taken out, is run over the residual, the
calibration's linearised refit (the nuisance) and the term's columns alike; the term is then
fitted to what is left (what the channel explains that the residual's own past does not). The
lag is the maximum of that fit's explained sum of squares, first on the search's grid, then by a
continuous 1-D search between the grid neighbours; the coefficient and its block (HAC)
covariance come from the same whitened fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg import solve_toeplitz
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

from ..design import column_basis
from . import channel_scores as cs

MAX_ORDER = 40  # the longest autoregression tried, in searched samples
MIN_ROWS_PER_ORDER = 20  # … and never more than one order per this many samples
LAG_XTOL = 1e-3  # the continuous lag search stops at this relative step (in log lag)


def ar_polynomial(e: np.ndarray, max_order: int = MAX_ORDER) -> np.ndarray:
    """[1, −φ₁ … −φ_p] of the autoregression of ``e`` whose order p ≤ max_order has the least
    AIC (Yule–Walker); [1] when none beats white noise."""
    e = np.asarray(e, np.float64) - float(np.mean(e))
    n = len(e)
    top = int(min(max_order, n // MIN_ROWS_PER_ORDER))
    acf = np.array([e[: n - k] @ e[k:] for k in range(top + 1)]) / max(n, 1)
    if top < 1 or acf[0] <= 0:
        return np.ones(1)
    best, poly = np.log(acf[0]), np.ones(1)
    for p in range(1, top + 1):
        phi = solve_toeplitz(acf[:p], acf[1 : p + 1])
        s2 = acf[0] - phi @ acf[1 : p + 1]
        if s2 <= 0:
            break
        aic = np.log(s2) + 2.0 * p / n
        if aic < best:
            best, poly = aic, np.concatenate([[1.0], -phi])
    return poly


@dataclass(frozen=True)
class Whitened:
    """The searched samples of a ``channel_scores.Frame`` through the residual's own filter:
    whitened residual ``r`` and orthonormal nuisance ``q``, the offset basis (unfiltered) and
    the filter ``poly``."""

    r: np.ndarray
    q: np.ndarray
    basis: np.ndarray
    poly: np.ndarray

    def filtered(self, z: np.ndarray) -> np.ndarray:
        """``z`` through the filter, its first (start-up) rows dropped."""
        return lfilter(self.poly, [1.0], z, axis=0)[len(self.poly) - 1 :]

    def fit(self, g: np.ndarray):
        """(ESS, β, whitened projected columns, their normal matrix) of the offset term β·g."""
        x = self.filtered(self.basis * np.asarray(g, np.float64)[:, None])
        x = x - self.q @ (self.q.T @ x)
        a = x.T @ x
        a = a + cs.RIDGE * (np.trace(a) + 1e-300) * np.eye(a.shape[0])
        xr = x.T @ self.r
        beta = np.linalg.solve(a, xr)
        return float(beta @ xr), beta, x, a

    def ess(self, g: np.ndarray) -> float:
        return self.fit(g)[0]

    def s2_after(self, ess: float) -> float:
        """The whitened residual variance left after a 3-column term with this ESS."""
        return max(float(self.r @ self.r) - ess, 0.0) / max(len(self.r) - self.q.shape[1] - 3, 1)

    def hac_cov(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(β, its covariance, inflation) as ``channel_scores.hac_cov``, on the whitened fit."""
        _, beta, x, a = self.fit(g)
        e = self.r - x @ beta
        return (beta, *cs.sandwich(x, e, a, self.q.shape[1]))


def whiten(fr: cs.Frame, e: np.ndarray) -> Whitened:
    """``fr`` through the autoregressive filter of ``e`` (its residual with the term out)."""
    poly = ar_polynomial(e)
    probe = Whitened(np.zeros(0), np.zeros((0, 0)), fr.bases["offset"], poly)
    q = column_basis(probe.filtered(fr.q))
    r = probe.filtered(fr.r)
    return Whitened(r - q @ (q.T @ r), q, fr.bases["offset"], poly)


def best_lag(wf: Whitened, lags: np.ndarray, coarse: np.ndarray, series: Callable[[float], np.ndarray]) -> float:
    """The lag of the largest whitened ESS: the best of ``lags`` (sorted, all > 0; ``coarse``
    (n, m) their series), then a bounded search in log lag between its neighbours;
    ``series(lag)`` the term's series at any lag."""
    ess = np.array([wf.ess(coarse[:, k]) for k in range(len(lags))])
    k = int(np.argmax(ess))
    lo, hi = np.log(lags[max(k - 1, 0)]), np.log(lags[min(k + 1, len(lags) - 1)])
    if hi - lo <= LAG_XTOL:
        return float(lags[k])
    opt = minimize_scalar(lambda v: -wf.ess(series(float(np.exp(v)))), bounds=(lo, hi), method="bounded",
                          options={"xatol": LAG_XTOL})
    return float(np.exp(opt.x)) if -opt.fun >= ess[k] else float(lags[k])
