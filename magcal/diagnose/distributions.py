"""The few tail probabilities and quantiles diagnosis needs (F, Student t, χ²), from
scipy.special: importing scipy.stats costs the command about half a second of start-up."""

from __future__ import annotations

from scipy import special


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """P(F ≥ x) for F with (dfn, dfd) degrees of freedom."""
    return float(special.fdtrc(dfn, dfd, max(float(x), 0.0)))


def f_isf(q: float, dfn: float, dfd: float) -> float:
    """x with P(F ≥ x) = q."""
    return float(special.fdtri(dfn, dfd, 1.0 - q))


def t_isf(q: float, df: float) -> float:
    """x with P(T ≥ x) = q for Student's t with df degrees of freedom."""
    return float(special.stdtrit(df, 1.0 - q))


def chi2_sf(x: float, df: float) -> float:
    return float(special.chdtrc(df, max(float(x), 0.0)))


def chi2_isf(q: float, df: float) -> float:
    return float(special.chdtri(df, q))
