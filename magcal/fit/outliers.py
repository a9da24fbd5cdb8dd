"""Outliers: the Smirnov–Grubbs test (seed 004) applied iteratively to fit residuals, with
critical values from the t distribution rather than a table, plus the robust scale used to
seed robust losses.

Grubbs (two-sided, level α): G = max|e_i − ē| / s, compared with

    G_crit(n) = (n − 1)/√n · √( t² / (n − 2 + t²) ),    t = t_{1 − α/(2n), n − 2}

The most extreme sample is removed while G > G_crit, recomputing ē and s each time. The test
assumes the clean residuals are Gaussian and independent; α is the chance of removing one
clean sample from a clean run (measured: see tests/test_fit_outliers.py).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

DEFAULT_ALPHA = 0.01


def grubbs_critical(n: int, alpha: float = DEFAULT_ALPHA) -> float:
    """Two-sided Grubbs critical value for n samples at level α."""
    if n < 3:
        raise ValueError(f"the Grubbs test needs at least 3 samples, got {n}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    t = stats.t.ppf(1.0 - alpha / (2.0 * n), n - 2)
    return float((n - 1) / np.sqrt(n) * np.sqrt(t * t / (n - 2 + t * t)))


def grubbs(residual, alpha: float = DEFAULT_ALPHA, max_fraction: float = 0.2) -> np.ndarray:
    """Indices (into ``residual``) that the iterated Grubbs test removes, in removal order.

    Stops when the most extreme remaining sample passes, when 3 samples remain, or when
    ``max_fraction`` of the samples have gone (beyond that the residuals are not "Gaussian
    plus a few outliers" and the test's premise is broken)."""
    e = np.asarray(residual, dtype=np.float64).reshape(-1)
    n = len(e)
    keep = np.ones(n, bool)
    removed: list[int] = []
    # running sums make each step O(n) for the arg-max only
    s1, s2, k = float(e.sum()), float(e @ e), n
    limit = int(max_fraction * n)
    while k > 3 and len(removed) < limit:
        mean = s1 / k
        var = (s2 - k * mean * mean) / (k - 1)
        if var <= 0:
            break
        dev = np.where(keep, np.abs(e - mean), -1.0)
        i = int(np.argmax(dev))
        if dev[i] / np.sqrt(var) <= grubbs_critical(k, alpha):
            break
        keep[i] = False
        removed.append(i)
        s1 -= e[i]
        s2 -= e[i] * e[i]
        k -= 1
    return np.asarray(removed, dtype=np.int64)


def robust_sigma(residual) -> float:
    """1.4826 · median absolute deviation from the median (σ for Gaussian residuals)."""
    e = np.asarray(residual, dtype=np.float64).reshape(-1)
    if len(e) == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(e - np.median(e))))
