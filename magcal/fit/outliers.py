"""Outliers: the Smirnov–Grubbs test (seed 004) applied iteratively to fit residuals, with
critical values from the t distribution (``fit.tails``) rather than a table, plus the robust scale used to
seed robust losses.

Grubbs (two-sided, level α): G = max|e_i − ē| / s, compared with

    G_crit(n) = (n − 1)/√n · √( t² / (n − 2 + t²) ),    t = t_{1 − α/(2n), n − 2}

The most extreme sample is removed while G > G_crit, recomputing ē and s each time. The test
assumes the clean residuals are Gaussian and independent; α is the chance of removing one
clean sample from a clean run (measured: see tests/test_fit_outliers.py).
"""

from __future__ import annotations

import functools

import numpy as np

from .tails import t_isf

DEFAULT_ALPHA = 0.01


def grubbs_critical(n, alpha: float = DEFAULT_ALPHA):
    """Two-sided Grubbs critical value for n samples at level α (n may be an array)."""
    na = np.asarray(n, dtype=np.float64)
    if np.any(na < 3):
        raise ValueError(f"the Grubbs test needs at least 3 samples, got {int(np.min(na))}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    t = t_isf(alpha / (2.0 * na), na - 2)
    g = (na - 1) / np.sqrt(na) * np.sqrt(t * t / (na - 2 + t * t))
    return float(g) if np.ndim(g) == 0 else g


@functools.lru_cache(maxsize=64)
def _critical_block(start: int, stop: int, alpha: float) -> np.ndarray:
    """Critical values for k = start, start − 1, … > stop (read-only). Kept: every fit of the
    same number of samples asks for the same block (a diagnosis fits its n samples six to eight
    times)."""
    out = np.atleast_1d(grubbs_critical(np.arange(start, stop, -1), alpha))
    out.flags.writeable = False
    return out


def grubbs(residual, alpha: float = DEFAULT_ALPHA, max_fraction: float = 0.2) -> np.ndarray:
    """Indices (into ``residual``) that the iterated Grubbs test removes, in removal order.

    Stops when the most extreme remaining sample passes, when 3 samples remain, or when
    ``max_fraction`` of the samples have gone (beyond that the residuals are not "Gaussian
    plus a few outliers" and the test's premise is broken). O(n log n): the sample farthest
    from the mean is always the smallest or the largest remaining one, so one sort suffices."""
    e = np.asarray(residual, dtype=np.float64).reshape(-1)
    n = len(e)
    order = np.argsort(e, kind="stable")
    v = e[order]
    lo, hi = 0, n - 1  # remaining samples are v[lo..hi]
    removed: list[int] = []
    s1, s2, k = float(v.sum()), float(v @ v), n
    limit = int(max_fraction * n)
    if n <= 3 or limit == 0:
        return np.zeros(0, dtype=np.int64)
    # critical values for k = n, n−1, …, computed (vectorised) a block at a time as needed
    last_k = max(n - limit, 3)
    crit = np.zeros(0)
    while k > 3 and len(removed) < limit:
        if n - k >= len(crit):
            start = n - len(crit)
            crit = np.concatenate([crit, _critical_block(start, max(start - 2 * len(crit) - 64, last_k - 1), alpha)])
        mean = s1 / k
        var = (s2 - k * mean * mean) / (k - 1)
        if var <= 0:
            break
        d_lo, d_hi = mean - v[lo], v[hi] - mean
        j = hi if d_hi >= d_lo else lo
        if max(d_lo, d_hi) / np.sqrt(var) <= crit[n - k]:
            break
        removed.append(int(order[j]))
        s1 -= v[j]
        s2 -= v[j] * v[j]
        k -= 1
        if j == hi:
            hi -= 1
        else:
            lo += 1
    return np.asarray(removed, dtype=np.int64)


def robust_sigma(residual) -> float:
    """1.4826 · median absolute deviation from the median (σ for Gaussian residuals)."""
    e = np.asarray(residual, dtype=np.float64).reshape(-1)
    if len(e) == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(e - np.median(e))))
