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

import functools
import math

import numpy as np

DEFAULT_ALPHA = 0.01

_lgamma = np.frompyfunc(math.lgamma, 1, 1)


def _ln_gamma(x) -> np.ndarray:
    return np.asarray(_lgamma(np.asarray(x, dtype=np.float64)), dtype=np.float64)


def beta_cf_numerator(k: int, x, a, b):
    """d_k of the continued fraction of the regularised incomplete beta function I_x(a, b)
    (DLMF 8.17.22), d_0 = 1; for a float or an array ``x`` alike."""
    if k == 0:
        return 1.0 + 0.0 * x
    if k % 2:
        m = (k - 1) // 2
        return -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
    m = k // 2
    return m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))


def _beta_cf(x, a, b, iterations: int = 500) -> np.ndarray:
    """1/(1 + d₁/(1 + d₂/(1 + …))), the continued fraction of the regularised incomplete beta
    function (DLMF 8.17.22), by the modified Lentz method; converges fast for
    x < (a + 1)/(a + b + 2)."""
    tiny = 1e-300
    f = np.full_like(x, tiny)
    c, d = f.copy(), np.zeros_like(x)
    for j in range(iterations):
        num = beta_cf_numerator(j, x, a, b)
        d = 1.0 + num * d
        d = 1.0 / np.where(np.abs(d) < tiny, tiny, d)
        c = 1.0 + num / c
        c = np.where(np.abs(c) < tiny, tiny, c)
        f = f * c * d
        if j > 1 and np.all(np.abs(c * d - 1.0) < 1e-15):
            break
    return f


def _t_log_sf(t, df, log_beta) -> np.ndarray:
    """ln P(T > t), t ≥ 0, given ln B(df/2, ½)."""
    x = df / (df + t * t)
    a, b = df / 2.0, 0.5
    direct = x < (a + 1.0) / (a + b + 2.0)
    front = a * np.log(x) + b * np.log1p(-x) - log_beta  # ln[x^a (1−x)^b / B(a, b)]
    cf_a = _beta_cf(np.where(direct, x, 0.0), a, b)
    cf_b = _beta_cf(np.where(direct, 0.0, 1.0 - x), b, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_i = np.where(direct, front + np.log(cf_a / a),
                         np.log1p(-np.minimum(np.exp(front) * cf_b / b, 1.0)))  # I_x = 1 − I_{1−x}(b, a)
    return np.log(0.5) + log_i


def t_log_sf(t, df) -> np.ndarray:
    """ln P(T > t) for Student's t with ``df`` degrees of freedom, t ≥ 0 (vectorised)."""
    t, df = np.broadcast_arrays(np.asarray(t, np.float64), np.asarray(df, np.float64))
    log_beta = _ln_gamma(df / 2) + math.lgamma(0.5) - _ln_gamma(df / 2 + 0.5)
    return _t_log_sf(t, df, log_beta)


def t_upper_quantile(p, df) -> np.ndarray:
    """t such that P(T > t) = p, for 0 < p < ½ (vectorised; Newton's method on ln P against
    ln t, started from the Cornish–Fisher expansion of Abramowitz & Stegun 26.7.5)."""
    p, df = np.broadcast_arrays(np.asarray(p, np.float64), np.asarray(df, np.float64))
    if np.any((p <= 0) | (p >= 0.5)) or np.any(df <= 0):
        raise ValueError("t_upper_quantile needs 0 < p < 0.5 and df > 0")
    q = np.sqrt(-2.0 * np.log(p))  # the normal upper quantile, A&S 26.2.23 (±4.5e-4)
    z = q - (2.515517 + 0.802853 * q + 0.010328 * q * q) / (1 + 1.432788 * q + 0.189269 * q * q + 0.001308 * q**3)
    t = z + (z**3 + z) / (4 * df) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)
    u = np.log(np.maximum(t, 1e-3))
    log_beta = _ln_gamma(df / 2) + math.lgamma(0.5) - _ln_gamma(df / 2 + 0.5)
    log_norm = -log_beta - 0.5 * np.log(df)  # the density's constant: 1/(√df B(df/2, ½))
    for _ in range(60):
        t = np.exp(u)
        log_sf = _t_log_sf(t, df, log_beta)
        log_pdf = log_norm - (df + 1) / 2 * np.log1p(t * t / df)
        slope = -t * np.exp(log_pdf - log_sf)  # d ln P / d ln t
        step = np.clip((log_sf - np.log(p)) / slope, -2.0, 2.0)
        u = u - step
        if np.all(np.abs(step) < 1e-12):  # ln t to 1e-12: t to 12 digits
            break
    return np.exp(u)


def grubbs_critical(n, alpha: float = DEFAULT_ALPHA):
    """Two-sided Grubbs critical value for n samples at level α (n may be an array)."""
    na = np.asarray(n, dtype=np.float64)
    if np.any(na < 3):
        raise ValueError(f"the Grubbs test needs at least 3 samples, got {int(np.min(na))}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    t = t_upper_quantile(alpha / (2.0 * na), na - 2)
    g = (na - 1) / np.sqrt(na) * np.sqrt(t * t / (na - 2 + t * t))
    return float(g) if np.ndim(g) == 0 else g


@functools.lru_cache(maxsize=64)
def _critical_block(start: int, stop: int, alpha: float) -> np.ndarray:
    """Critical values for k = start, start − 1, … > stop (read-only). Kept: every fit of the
    same number of samples asks for the same block (a diagnosis fits its n samples six to eight
    times), and each costs a t quantile by Newton's method on a continued fraction."""
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
