"""The recording's own slow wander as an uncertainty of a slow term's coefficient.

A channel that varies slowly (a temperature swing of about a cycle, time itself) takes into its
coefficient whatever part of the recording's offset wander happens to have its shape. That part
is exactly what a residual cannot show: the fit removes it together with the term, so no
covariance estimated from the residual (block sums, even bias-corrected) carries it, and a
twin whose wander was learned at the recording's faster scales draws too little of it.

Here the wander is read where the residual still shows it and carried to where it does not. The
offset wander is written as a random polynomial in time, b(t) = Σ_d P̂_d(τ) a_d (P̂_d the
Legendre polynomial of degree d scaled to unit mean square on [−1, 1], a_d a random 3-vector):
for a stationary wander the variance of a_d is its spectrum near the frequency d / (2·duration),
and an Ornstein–Uhlenbeck wander (the sensor model's, magcal.sim.wander) gives
s_d = level / (1 + (d / knee)²): flat below its knee, falling as a random walk's above. The coefficients of degrees ``FIRST_SEEN``…
``DEGREE`` are estimated by regressing the residual on them with every column of the design in
place, and s_d (level ≥ 0, knee) is fitted to them by maximum likelihood,
each a_d,j ~ N(0, s_d + w_d,j) with w_d,j its white-noise variance. The wander's share of a
term's coefficient is then Σ_d s_d M_d M_dᵀ, M_d the coefficient a wander of shape P̂_d·(W u)
would give the term in the same regression (degrees 1…``DEGREE``, the unseen slow ones
included) — the long-run variance at the term's own time scales.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre

from .design import column_basis
from .null import WHITE_LEVEL

DEGREE = 8  # the wander next to the slow terms' own time scales: the degrees just above the fitted ones
FIRST_SEEN = 3  # degrees 0…2 (hard iron, the drift, the quadratic nuisance) are fitted by the design
KNEES = np.concatenate([np.geomspace(0.25, 64.0, 33), [np.inf]])  # the knee, in degrees (∞: flat)
KNEE_DROP = 1.353  # half the 90 % point of χ²₁: a one-sided 95 % profile-likelihood bound


@dataclass(frozen=True)
class SlowSpectrum:
    """The fitted variance of the wander's Legendre coefficient of degree d (µT²): an
    Ornstein–Uhlenbeck (Lorentzian) spectrum, level / (1 + (d / knee)²) — flat below the knee,
    falling as a random walk's above it."""

    level_ut2: float
    knee: float  # in degrees (∞: flat)
    white_ut2: float = 0.0  # the variance of the rest of the residual, per sample

    def variance(self, degree: np.ndarray) -> np.ndarray:
        return self.level_ut2 / (1.0 + (np.asarray(degree, np.float64) / self.knee) ** 2)


def shapes(t_s: np.ndarray, offset_directions: np.ndarray, degree: int = DEGREE) -> np.ndarray:
    """(degree, n, 3): P̂_d(τ)·(W u) for d = 1…degree, τ the time scaled to [−1, 1]."""
    t = np.asarray(t_s, np.float64)
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    tau = 2.0 * (t - t[0]) / span - 1.0 if span > 0 else np.zeros(len(t))
    vand = legendre.legvander(tau, degree)[:, 1:] * np.sqrt(2.0 * np.arange(1, degree + 1) + 1.0)
    return vand.T[:, :, None] * offset_directions[None, :, :]


def fit_spectrum(coef: np.ndarray, white: np.ndarray, degrees: np.ndarray) -> SlowSpectrum:
    """coef[d, j] ~ N(0, s_d + white[d, j]), s_d = level / (1 + (d / knee)²): for each knee on
    KNEES the level (≥ 0) of maximum likelihood; of the knees the seen degrees do not reject
    (profile likelihood within KNEE_DROP of its maximum: a one-sided 95 % bound), the one that
    puts the most variance at degree 1 — below the seen degrees the data cannot place the knee,
    and a region must not assume the flattest spectrum they allow."""
    c2 = coef**2
    top = max(float(c2.max(initial=0.0)), float(white.max(initial=0.0)), 1e-300)
    levels = np.concatenate([[0.0], top * np.logspace(-8, 3, 221)])  # at the lowest seen degree
    fits = []
    for knee in KNEES:
        shape = (1.0 + (degrees[0] / knee) ** 2) / (1.0 + (degrees.astype(float) / knee) ** 2)
        s = levels[:, None, None] * shape[None, :, None] + white[None]
        nll = 0.5 * np.sum(np.log(s) + c2[None] / s, axis=(1, 2))
        i = int(np.argmin(nll))
        fits.append((float(nll[i]), SlowSpectrum(float(levels[i] * (1.0 + (degrees[0] / knee) ** 2)), float(knee))))
    least = min(f[0] for f in fits)
    allowed = [sp for nll, sp in fits if nll <= least + KNEE_DROP]
    return max(allowed, key=lambda sp: float(sp.variance(1.0)))


def spectrum_of(x: np.ndarray, e: np.ndarray, shp: np.ndarray) -> SlowSpectrum:
    """The wander's Legendre spectrum fitted to the residual e of design x (see the module)."""
    q = column_basis(x)
    seen = shp[FIRST_SEEN - 1 :]  # (m, n, 3)
    m = len(seen)
    w = np.concatenate(list(seen), axis=1)  # (n, 3m)
    w = w - q @ (q.T @ w)
    r = e - q @ (q.T @ e)
    g = w.T @ w
    ginv = np.linalg.pinv(g, rcond=1e-10, hermitian=True)
    a = ginv @ (w.T @ r)
    dof = max(len(e) - q.shape[1] - 3 * m, 1)
    sigma2 = float(np.sum((r - w @ a) ** 2)) / dof
    white = sigma2 * np.diag(ginv).reshape(m, 3)
    fitted = fit_spectrum(a.reshape(m, 3), white, np.arange(FIRST_SEEN, FIRST_SEEN + m))
    return SlowSpectrum(fitted.level_ut2, fitted.knee, sigma2)


@dataclass(frozen=True)
class SlowShare:
    """A term's coefficient covariance from the slow wander, and the degrees of freedom of the
    spectrum it rests on (the seen coefficients less the two fitted parameters)."""

    cov: np.ndarray
    dof: float


@dataclass(frozen=True)
class _Regression:
    """What every group's coefficient_cov reads of the regression on all of x: each column's
    scale, the coefficients of every column for each wander shape (scaled columns), and the
    pseudo-inverse of the scaled Gram matrix."""

    scale: np.ndarray
    b: np.ndarray  # (p, 3·D)
    ginv: np.ndarray  # (p, p)


def _regression(x: np.ndarray, shp: np.ndarray) -> _Regression:
    scale = np.sqrt(np.maximum((x * x).sum(axis=0), 1e-300))
    xs = x / scale
    rhs = np.concatenate(list(shp), axis=1)  # (n, 3·D)
    return _Regression(scale, np.linalg.lstsq(xs, rhs, rcond=1e-10)[0],
                       np.linalg.pinv(xs.T @ xs, rcond=1e-10, hermitian=True))


def coefficient_cov(x: np.ndarray, cols: np.ndarray, shp: np.ndarray, spectrum: SlowSpectrum,
                    reg: _Regression | None = None) -> np.ndarray:
    """(len(cols), len(cols)): Σ_d s_d M_d M_dᵀ + σ² [(XᵀX)⁻¹]_cols, M_d the coefficients of x's
    columns ``cols`` (in their own units) that a wander of shape P̂_d·(W u) gets in the
    regression on all of x, σ² the rest of the residual taken as white: the coefficient's
    covariance under the fitted wander. ``reg``: ``_regression(x, shp)`` when already made
    (it is the same for every group of x's columns)."""
    reg = reg or _regression(x, shp)
    scale = reg.scale
    b = reg.b[cols] / scale[cols, None]  # (k, 3·D)
    s = np.repeat(spectrum.variance(np.arange(1, len(shp) + 1)), 3)
    ginv = reg.ginv[np.ix_(cols, cols)] / np.outer(scale[cols], scale[cols])
    return (b * s) @ b.T + spectrum.white_ut2 * ginv


def wander_covariances(x: np.ndarray, e: np.ndarray, t_s: np.ndarray, offset_directions: np.ndarray,
                       groups: dict, model_cols: np.ndarray) -> dict:
    """Per named group of x's columns: its coefficient's covariance from the recording's own
    slow offset wander (the module's construction), a SlowShare. The wander's spectrum is read from the
    residual of the model's own columns ``model_cols`` (a slow candidate left out of the model
    would take the very shapes the spectrum is read from); the coefficients are those of the
    regression on all of x."""
    if not groups or len(e) < 10 * (x.shape[1] + 3 * DEGREE):
        return {}
    shp = shapes(t_s, offset_directions)
    spectrum = spectrum_of(x[:, np.asarray(model_cols)], e, shp)
    dof = 3.0 * (DEGREE - FIRST_SEEN + 1) - 2.0
    reg = _regression(x, shp)  # one regression on all of x serves every group
    return {g: SlowShare(coefficient_cov(x, np.asarray(cols), shp, spectrum, reg), dof) for g, cols in groups.items()}


def shows_wander(x: np.ndarray, e: np.ndarray, t_s: np.ndarray, offset_directions: np.ndarray, first: int,
                 q: np.ndarray | None = None) -> bool:
    """Whether the residual e of design x shows an offset wander of Legendre degrees
    ``first``…DEGREE: the F test of those shapes (``shapes``) added to x rejects at
    WHITE_LEVEL, the level at which a residual gets no twin either (exact for white noise; a
    degree the design's columns nearly take counts for what is left of it). True where the
    recording is too short to tell (as ``wander_covariances``). ``q``: ``column_basis(x)`` when
    the caller has it."""
    n = len(e)
    if n < 10 * (x.shape[1] + 3 * DEGREE):
        return True
    from ..fit.tails import f_sf

    q = column_basis(x) if q is None else q
    w = np.concatenate(list(shapes(t_s, offset_directions)[first - 1 :]), axis=1)
    qw = column_basis(w - q @ (q.T @ w))
    r = e - q @ (q.T @ e)
    explained = qw.T @ r
    k, dof = qw.shape[1], n - q.shape[1] - qw.shape[1]
    rest = float(r @ r) - float(explained @ explained)
    if k == 0 or dof <= 0 or not rest > 0:
        return True
    return float(f_sf(float(explained @ explained) / k / (rest / dof), k, dof)) <= WHITE_LEVEL
