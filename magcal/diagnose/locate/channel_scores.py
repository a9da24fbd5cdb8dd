"""The arithmetic behind ``channel_forms``: how well a family of channel terms explains a residual.

A channel term is a basis B (n, p) — the offset directions W·u, the field F (an isotropic gain)
or F·u_k² (a gain per axis) — times one or more series built from the channel (the channel
delayed, low-passed, squared, its cosine and sine, a step at a threshold). A *family* holds
many candidates of one form (one per lag, threshold or unit) as series of shape (n, m, s): the
candidate j uses the s series ``series[:, j, :]`` jointly with the basis (p·s columns).

Every candidate is judged after the calibration's own linearised refit (offset, radius and the
six shape terms) is projected out, so a term the calibration can already absorb scores nothing.
Its explained sum of squares over the residual variance is put on one scale across column
counts (−log₁₀ of the χ² tail with that many degrees of freedom), which is what the null
(circular shifts of the channel against the residual) is taken over.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from magcal.fit import tails

RIDGE = 1e-9
N_BLOCKS = 20  # contiguous blocks for the autocorrelation-robust (HAC) covariance
T_975_19 = 2.093  # Student t, 97.5 %, 19 degrees of freedom (N_BLOCKS − 1)
CHI2_1_95 = 3.841
CHI2_1_999 = 10.828


@dataclass(frozen=True)
class Family:
    """Candidates of one form on one channel: ``series`` (n, m, s), ``values`` (m,) the lag,
    threshold or unit code of each, ``basis`` "offset", "gain" or "axis_gain"."""

    form: object
    channel: str
    basis: str
    series: np.ndarray
    values: np.ndarray

    def rolled(self, shift: int) -> "Family":
        return Family(self.form, self.channel, self.basis, np.roll(self.series, shift, axis=0), self.values)


def n_columns(fam: Family) -> int:
    """The columns of one candidate of ``fam``."""
    return {"offset": 3, "gain": 1, "axis_gain": 3}[fam.basis] * fam.series.shape[2]


@dataclass(frozen=True)
class Pick:
    """The best candidate of a search: its family, index, normal score, and the explained sums
    of squares of every candidate of that family (whitened ones where ``white`` is set:
    ``channel_whiten``)."""

    fam: Family
    j: int
    score: float
    ess: np.ndarray
    white: object = None  # for a lag: the whitened frame its lag, ESS and coefficient come from


@dataclass(frozen=True)
class Frame:
    """The searched samples: radial residual ``r`` with the calibration's refit projected out,
    the orthonormal nuisance ``q``, the bases, the residual variance ``s2``, the row index
    ``rows`` into the recording and the times ``t_s``."""

    r: np.ndarray
    q: np.ndarray
    bases: dict
    s2: float
    rows: np.ndarray
    t_s: np.ndarray

    def f_ratio(self, ess: np.ndarray, k: int) -> np.ndarray:
        """ESS over the variance left after the candidate's own fit (an F ratio × k): a shifted
        channel that catches a share of an effect still in the residual is judged against a
        residual that still holds the rest of it."""
        dof = max(len(self.r) - self.q.shape[1] - k, 1)
        left = np.maximum(float(self.r @ self.r) - np.asarray(ess), 1e-300 * float(self.r @ self.r) + 1e-300)
        return np.asarray(ess) / (left / dof)

    def s2_after(self, ess: float, k: int) -> float:
        """The residual variance left after a candidate with this ESS and k columns."""
        return max(float(self.r @ self.r) - float(ess), 0.0) / max(len(self.r) - self.q.shape[1] - k, 1)

    def with_r(self, r: np.ndarray) -> "Frame":
        r = r - self.q @ (self.q.T @ r)
        s2 = float(r @ r) / max(len(r) - self.q.shape[1], 1)
        return Frame(r, self.q, self.bases, s2, self.rows, self.t_s)


def frame(r_ut: np.ndarray, u: np.ndarray, w: np.ndarray, field_ut: float, rows: np.ndarray, t_s: np.ndarray) -> Frame:
    """The frame of the samples ``rows``: the nuisance is the linearised refit of the ellipsoid
    (three offset directions W·u and the six products u_i u_j, whose sum is the radius)."""
    u = u[rows]
    wu = u @ w
    prods = np.column_stack([u[:, 0] ** 2, u[:, 1] ** 2, u[:, 2] ** 2, u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]])
    q, _ = np.linalg.qr(np.column_stack([wu, prods]))
    bases = {"offset": wu, "gain": np.full((len(u), 1), field_ut), "axis_gain": field_ut * u**2}
    return Frame(np.zeros(len(u)), q, bases, 1.0, rows, t_s[rows]).with_r(np.asarray(r_ut, np.float64)[rows])


def log10_p(ess_over_s2, k: int) -> np.ndarray:
    """−log₁₀ P(χ²_k ≥ x): one scale across column counts (a form with more columns must
    explain more to score the same), finite where the p-value underflows."""
    return tails.chi2_log10_sf(ess_over_s2, k)


def scores(fr: Frame, fam: Family, design=None) -> tuple[np.ndarray, np.ndarray]:
    """(explained sum of squares (m,), coefficients (m, p·s)) of every candidate of ``fam``;
    ``design``: ``design_of(fr, fam)`` when already made (it does not depend on the residual, so
    frames that differ only in it share one)."""
    design = design_of(fr, fam) if design is None else design
    if fam.series.shape[2] == 1:
        return _scores_single(fr.bases[fam.basis], fam.series[:, :, 0], fr.r, design)
    out = [_solved(xt, a, fr.r)[:2] for xt, a in design]
    return np.array([e for e, _ in out]), np.array([c for _, c in out])


def design_of(fr: Frame, fam: Family):
    """What scoring ``fam`` on ``fr`` takes from the columns and the nuisance alone, not from the
    residual: for one series per candidate the normal matrices (m, p, p), else each candidate's
    projected columns and normal matrix."""
    b = fr.bases[fam.basis]
    if fam.series.shape[2] == 1:
        return _normal_single(b, fam.series[:, :, 0], fr.q)
    return [_projected(columns(b, fam.series[:, j, :]), fr.q) for j in range(fam.series.shape[1])]


def _normal_single(b: np.ndarray, g: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The normal matrices (ridge included) of the columns b·g_j with the nuisance q projected
    out, vectorised over the m series of g."""
    n, p = b.shape
    m = g.shape[1]
    bb = (b[:, :, None] * b[:, None, :]).reshape(n, p * p)
    xtx = (bb.T @ g**2).T.reshape(m, p, p)
    qx = np.stack([(q * b[:, [a]]).T @ g for a in range(p)], axis=1)  # (nq, p, m)
    xtx = xtx - np.einsum("qam,qbm->mab", qx, qx)
    ridge = RIDGE * (np.trace(xtx, axis1=1, axis2=2)[:, None, None] + 1e-300) * np.eye(p)
    return xtx + ridge


def _scores_single(b: np.ndarray, g: np.ndarray, r: np.ndarray, normal: np.ndarray):
    """Vectorised over the m series of g: columns b·g_j (p of them) for each j, whose normal
    matrices ``_normal_single`` made."""
    xtr = ((b * r[:, None]).T @ g).T  # (m, p)
    beta = np.linalg.solve(normal, xtr[:, :, None])[:, :, 0]
    return np.sum(beta * xtr, axis=1), beta


def columns(b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The p·s columns basis × series, series-major."""
    return np.concatenate([b * s[:, [k]] for k in range(s.shape[1])], axis=1)


def _projected(x: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the columns with the nuisance q projected out, their normal matrix with the ridge)."""
    xt = x - q @ (q.T @ x)
    a = xt.T @ xt
    return xt, a + RIDGE * (np.trace(a) + 1e-300) * np.eye(a.shape[0])


def _solved(xt: np.ndarray, a: np.ndarray, r: np.ndarray) -> tuple[float, np.ndarray]:
    """(explained square, coefficients) of r on the projected columns ``xt`` (normal matrix ``a``)."""
    beta = np.linalg.solve(a, xt.T @ r)
    return float(beta @ (xt.T @ r)), beta


def _fit(x: np.ndarray, r: np.ndarray, q: np.ndarray):
    xt, a = _projected(x, q)
    return (*_solved(xt, a, r), xt, a)


def term(fr: Frame, fam: Family, j: int) -> np.ndarray:
    """The fitted radial term of candidate j (projected like the residual)."""
    _, beta, xt, _ = _fit(columns(fr.bases[fam.basis], fam.series[:, j, :]), fr.r, fr.q)
    return xt @ beta


def hac_cov(fr: Frame, fam: Family, j: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(coefficients, their covariance, inflation) of candidate j: the sandwich over contiguous
    blocks (the residual's own autocorrelation), never below the white-noise covariance;
    inflation = how much larger than white its trace is."""
    _, beta, xt, a = _fit(columns(fr.bases[fam.basis], fam.series[:, j, :]), fr.r, fr.q)
    return (beta, *sandwich(xt, fr.r - xt @ beta, a, fr.q.shape[1]))


def sandwich(xt: np.ndarray, e: np.ndarray, a: np.ndarray, n_nuisance: int) -> tuple[np.ndarray, float]:
    """(covariance, inflation) of a fit with projected columns ``xt``, residual ``e`` and normal
    matrix ``a``: the block sandwich, never below the white-noise covariance."""
    ainv = np.linalg.inv(a)
    edges = np.linspace(0, len(e), N_BLOCKS + 1).astype(int)
    s = np.array([xt[i:k].T @ e[i:k] for i, k in zip(edges[:-1], edges[1:])])
    meat = s.T @ s * N_BLOCKS / (N_BLOCKS - 1)
    white = ainv * float(e @ e) / max(len(e) - a.shape[0] - n_nuisance, 1)
    hac = ainv @ meat @ ainv
    infl = max(float(np.trace(hac) / max(np.trace(white), 1e-300)), 1.0)
    return (hac if infl > 1.0 else white), infl


def profile(ess: np.ndarray, j: int, s2: float, infl: float) -> np.ndarray:
    """The candidates whose fit is within the 95 % profile of the best (j): ESS within
    χ²₁(95 %) × σ² (the variance left after j's fit) × inflation of its ESS — the lag's own
    uncertainty — and j's neighbours."""
    near = ess >= ess[j] - CHI2_1_95 * s2 * infl
    near[max(j - 1, 0):j + 2] = True  # the grid's own step is part of the lag's uncertainty
    return np.flatnonzero(near)


def gumbel_threshold(null_max: np.ndarray, alpha: float) -> float:
    """The (1 − alpha) quantile of a Gumbel law fitted by moments to the null maxima, and never
    below their largest value."""
    mu, sd = float(np.mean(null_max)), float(np.std(null_max, ddof=1))
    beta = sd * np.sqrt(6.0) / np.pi
    loc = mu - 0.5772156649 * beta
    return max(loc - beta * np.log(-np.log(1.0 - alpha)), float(np.max(null_max)))


def slow_energies(fr: Frame, term_r: np.ndarray, n_blocks: int = N_BLOCKS) -> tuple[float, float]:
    """(mean square per sample of the term's block fits, of what is left's block fits beyond the
    noise): each contiguous block's residual fitted with its own offset and radius (the slow
    wander a recording carries); a slow term must carry far more of that than it leaves."""
    e = fr.r - term_r
    b = np.column_stack([fr.bases["offset"], np.ones(len(e))])
    edges = np.linspace(0, len(e), n_blocks + 1).astype(int)
    e_term = e_rem = rss = 0.0
    for i, k in zip(edges[:-1], edges[1:]):
        a = b[i:k]
        pinv = np.linalg.pinv(a)
        fit_e, fit_t = a @ (pinv @ e[i:k]), a @ (pinv @ term_r[i:k])
        e_rem += float(fit_e @ fit_e)
        e_term += float(fit_t @ fit_t)
        rss += float(np.sum((e[i:k] - fit_e) ** 2))
    n = len(e)
    s2 = rss / max(n - 4 * n_blocks, 1)
    return e_term / n, max(e_rem - 4 * n_blocks * s2, 0.0) / n
