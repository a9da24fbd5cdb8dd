"""The few tail probabilities and quantiles diagnosis needs (F, Student t, χ²), in plain
Python: importing scipy.special costs the command about 0.17 s of CPU at start-up, more than a
whole diagnosis of 5000 samples is allowed.

F and t tails are regularised incomplete beta functions, χ² tails regularised incomplete gamma
functions; both are evaluated by their continued fractions (modified Lentz, DLMF 8.17.22 and
8.9.2) or series, in logarithms so that a tail of 1e-300 is still a number. Quantiles invert
the tails by bisection on the logarithm of the argument (to 1e-13 relative).

>>> round(f_sf(4.0, 3, 20), 6)   # scipy.special.fdtrc(3, 20, 4.0) = 0.022076...
0.022077
>>> round(f_isf(0.01, 2, 30), 4)  # scipy.special.fdtri(2, 30, 0.99) = 5.3903...
5.3903
>>> round(chi2_sf(30.0, 20), 6)   # scipy.special.chdtrc(20, 30.0) = 0.069854...
0.069854
>>> round(t_isf(0.025, 10), 4)    # scipy.special.stdtrit(10, 0.975) = 2.2281...
2.2281
"""

from __future__ import annotations

import math

from ..fit.outliers import beta_cf_numerator

_TINY = 1e-300
_EPS = 1e-15


def _log_beta_cf(x: float, a: float, b: float) -> float:
    """ln of the continued fraction of I_x(a, b) (converges fast for x < (a + 1)/(a + b + 2)).
    The same fraction (the same terms) as fit.outliers._beta_cf, iterated here in scalar Python on
    purpose: the quantiles below evaluate it inside a bisection, where numpy's per-call cost on 0-d arrays
    made them 20× slower (1.6 s against 0.085 s for 400 quantiles and tails)."""
    f = c = _TINY
    d = 0.0
    log_f = math.log(_TINY)
    for k in range(2000):
        num = beta_cf_numerator(k, x, a, b)
        d = 1.0 + num * d
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = 1.0 + num / c
        c = c if abs(c) > _TINY else _TINY
        log_f += math.log(abs(c * d))
        f = c * d
        if k > 1 and abs(f - 1.0) < _EPS:
            break
    return log_f


def log_betainc(x: float, a: float, b: float) -> float:
    """ln I_x(a, b), the regularised incomplete beta function."""
    if x <= 0.0:
        return -math.inf
    if x >= 1.0:
        return 0.0
    log_front = a * math.log(x) + b * math.log1p(-x) - (math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b))
    if x < (a + 1.0) / (a + b + 2.0):
        return log_front + _log_beta_cf(x, a, b) - math.log(a)
    other = math.exp(log_front + _log_beta_cf(1.0 - x, b, a) - math.log(b))  # I_x = 1 − I_{1−x}(b, a)
    return math.log1p(-min(other, 1.0)) if other < 1.0 else -math.inf


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """P(F ≥ x) for F with (dfn, dfd) degrees of freedom."""
    x = max(float(x), 0.0)
    if x == 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    return math.exp(log_betainc(dfd / (dfd + dfn * x), dfd / 2.0, dfn / 2.0))


def _invert(log_sf, q: float) -> float:
    """x > 0 with sf(x) = q, for a decreasing tail given as ln sf(x): bisection on ln x, in a
    bracket widened until it holds the answer."""
    target = math.log(q)
    a, b = -4.0, 4.0
    while a > -700.0 and log_sf(math.exp(a)) <= target:
        a *= 2.0
    while b < 700.0 and log_sf(math.exp(b)) > target:
        b *= 2.0
    for _ in range(int(math.ceil(math.log2((b - a) / 1e-13)))):
        mid = 0.5 * (a + b)
        if log_sf(math.exp(mid)) > target:
            a = mid
        else:
            b = mid
    return math.exp(0.5 * (a + b))


def f_isf(q: float, dfn: float, dfd: float) -> float:
    """x with P(F ≥ x) = q."""
    return _invert(lambda x: log_betainc(dfd / (dfd + dfn * x), dfd / 2.0, dfn / 2.0), q)


def t_isf(q: float, df: float) -> float:
    """x with P(T ≥ x) = q for Student's t with df degrees of freedom (0 < q < 1)."""
    if q == 0.5:
        return 0.0
    if q > 0.5:
        return -t_isf(1.0 - q, df)
    # P(T ≥ x) = ½ I_{df/(df + x²)}(df/2, ½) for x > 0
    return _invert(lambda x: math.log(0.5) + log_betainc(df / (df + x * x), df / 2.0, 0.5), q)


def _log_gammaincc(a: float, x: float) -> float:
    """ln Q(a, x), the regularised upper incomplete gamma function."""
    if x <= 0.0:
        return 0.0
    log_front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:  # the series of P(a, x), then Q = 1 − P
        term = total = 1.0 / a
        for n in range(1, 5000):
            term *= x / (a + n)
            total += term
            if term < total * _EPS:
                break
        p = math.exp(log_front + math.log(total))
        return math.log1p(-p) if p < 1.0 else -math.inf
    b = x + 1.0 - a  # the continued fraction of Q (Lentz)
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for n in range(1, 5000):
        an = -n * (n - a)
        b += 2.0
        d = an * d + b
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = b + an / c
        c = c if abs(c) > _TINY else _TINY
        h *= d * c
        if abs(d * c - 1.0) < _EPS:
            break
    return log_front + math.log(h)


def chi2_sf(x: float, df: float) -> float:
    """P(χ² ≥ x) with df degrees of freedom."""
    return math.exp(_log_gammaincc(df / 2.0, max(float(x), 0.0) / 2.0))


def chi2_isf(q: float, df: float) -> float:
    """x with P(χ² ≥ x) = q."""
    return _invert(lambda x: _log_gammaincc(df / 2.0, x / 2.0), q)
