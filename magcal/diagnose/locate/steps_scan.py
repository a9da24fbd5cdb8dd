"""The arithmetic behind ``steps``: local regressions of the radial residual on the directions.

After a calibration h = W(m − b), a change δ of the raw offset moves the radial residual by
u·(Wδ) and a small change E of the shape (h → (I + E)h) by F·uᵀEu, u the unit direction and F
the field. So offsets and shapes are regressions of r on ``U`` (3 columns) and ``Q`` (the 6
quadratic terms of u, times F). A step is judged locally, in a window of ±``half_s`` around the
candidate time, against an offset that wanders as a quadratic in time over that window (a slow
wander or a ramp is absorbed; a jump is not). ``inflation`` measures how much more the
recording's own residual wanders than white noise would, on the same direction-weighted sums
the tests use, so every χ² is judged against the recording's structure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHI2_1_MEDIAN = 0.4549364231195724  # median of χ²₁: a block sum's variance from the median of its squares


@dataclass(frozen=True)
class Fit:
    """One least-squares fit: coefficients, residual sum of squares, (XᵀX)⁻¹, samples, columns."""

    coef: np.ndarray
    rss: float
    xtx_inv: np.ndarray
    n: int
    p: int


def lsq(x: np.ndarray, r: np.ndarray) -> Fit:
    """Least squares of ``r`` on the columns of ``x`` (pseudo-inverse where a column is undetermined)."""
    coef, *_ = np.linalg.lstsq(x, r, rcond=None)
    e = r - x @ coef
    return Fit(coef, float(e @ e), np.linalg.pinv(x.T @ x), len(r), x.shape[1])


def quad(u: np.ndarray, field_ut: float) -> np.ndarray:
    """The 6 shape columns F·(ux², uy², uz², 2uxuy, 2uxuz, 2uyuz): r's change under h → (I + E)h."""
    x, y, z = u.T
    return field_ut * np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z])


def hats(t_s: np.ndarray, knot_s: float) -> np.ndarray:
    """Piecewise-linear (hat) basis in time with knots every ``knot_s``: a slowly wandering level."""
    t0, t1 = float(t_s[0]), float(t_s[-1])
    k = max(1, int(np.ceil((t1 - t0) / knot_s)))
    knots = np.linspace(t0, t1, k + 1)
    step = knots[1] - knots[0] if k else 1.0
    return np.clip(1.0 - np.abs(t_s[:, None] - knots[None, :]) / step, 0.0, None)


def wander_columns(u: np.ndarray, t_s: np.ndarray, knot_s: float) -> np.ndarray:
    """U times each hat: an offset that wanders piecewise-linearly in time."""
    h = hats(t_s, knot_s)
    return (h[:, :, None] * u[:, None, :]).reshape(len(u), -1)


def inflation(e: np.ndarray, cols: np.ndarray, block: int) -> float:
    """f² ≥ 1: how much the variance of a sum of ``block`` neighbouring residuals weighted by
    ``cols`` (U for offsets, Q for shapes) exceeds ``block`` times that of one — the
    recording's own autocorrelation, on the sums a regression on those columns adds up. Robust
    (median of squared block sums), so one stretch with a step or a burst in it does not set it."""
    block = max(1, int(block))
    nb = len(e) // block
    k = cols.shape[1]
    if nb < 4:
        return 1.0
    z = (e[: nb * block, None] * cols[: nb * block]).reshape(nb, block, k)
    sums = z.sum(axis=1)
    one = np.median(z.reshape(-1, k) ** 2, axis=0) / CHI2_1_MEDIAN
    many = np.median(sums**2, axis=0) / CHI2_1_MEDIAN
    ratio = many / np.maximum(block * one, 1e-300)
    return float(max(1.0, np.median(ratio)))


def local_design(u: np.ndarray, t_s: np.ndarray, tau_s: float, half_s: float) -> np.ndarray:
    """[U, U·s, U·s²] with s = (t − τ)/half: a local offset wandering as a quadratic in time."""
    s = ((t_s - tau_s) / half_s)[:, None]
    return np.hstack([u, u * s, u * s * s])


def step_gain(u, t_s, r, tau_s: float, half_s: float) -> tuple[float, Fit]:
    """(ΔRSS of adding an offset step at τ to the local wander, the fit with the step): the
    step's coefficients are the last three."""
    base = local_design(u, t_s, tau_s, half_s)
    after = u * (t_s >= tau_s)[:, None]
    f0 = lsq(base, r)
    f1 = lsq(np.hstack([base, after]), r)
    return f0.rss - f1.rss, f1


def window(t_s: np.ndarray, tau_s: float, half_s: float) -> slice:
    """The samples within ±half of τ."""
    a = int(np.searchsorted(t_s, tau_s - half_s, "left"))
    b = int(np.searchsorted(t_s, tau_s + half_s, "right"))
    return slice(a, b)


def candidates(t_s: np.ndarray, half_s: float, per_half: int = 10) -> np.ndarray:
    """Candidate times every half/``per_half``, at least half/2 from either end."""
    lo, hi = t_s[0] + 0.5 * half_s, t_s[-1] - 0.5 * half_s
    if hi <= lo:
        return np.zeros(0)
    return np.arange(lo, hi, half_s / per_half)


def support(t_s: np.ndarray, tau_s: float, half_s: float, min_n: int) -> bool:
    """Both sides of τ within the window hold at least ``min_n`` samples."""
    w = window(t_s, tau_s, half_s)
    k = int(np.searchsorted(t_s, tau_s, "left"))
    return (k - w.start) >= min_n and (w.stop - k) >= min_n


def tail_grams(z: np.ndarray, r: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each start index (ascending), Σ_{i ≥ start} zᵢzᵢᵀ and Σ_{i ≥ start} zᵢrᵢ — the
    normal equations of every 'after τ' column set in one pass over the samples."""
    p = z.shape[1]
    grams = np.zeros((len(starts), p, p))
    cross = np.zeros((len(starts), p))
    g, c = np.zeros((p, p)), np.zeros(p)
    stop = len(z)
    for k in range(len(starts) - 1, -1, -1):
        block = slice(int(starts[k]), stop)
        g = g + z[block].T @ z[block]
        c = c + z[block].T @ r[block]
        grams[k], cross[k] = g, c
        stop = int(starts[k])
    return grams, cross


def solve_rss(xtx: np.ndarray, xtr: np.ndarray, rtr: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(RSS, coefficients, (XᵀX)⁻¹) from the normal equations."""
    inv = np.linalg.pinv(xtx)
    coef = inv @ xtr
    return float(rtr - coef @ xtr), coef, inv


class Moments:
    """Prefix sums of the local step test's normal equations, so the test at every candidate
    time (window [lo, hi), step at k, local time s = (t − a)/half) costs one 12×12 solve
    instead of a regression on the window: moments of uuᵀ·x^j (j ≤ 4) and r·u·x^j (j ≤ 2)
    with x = (t − t̄)/half, re-centred on a by the binomial expansion."""

    def __init__(self, u: np.ndarray, t_s: np.ndarray, r: np.ndarray, half_s: float):
        self.t0, self.half = float(np.mean(t_s)), float(half_s)
        x = (t_s - self.t0) / self.half
        pw = x[:, None] ** np.arange(5)[None, :]
        uu = u[:, :, None] * u[:, None, :]
        self.uu = _prefix(pw[:, :, None, None] * uu[:, None, :, :])  # (n+1, 5, 3, 3)
        self.ru = _prefix(pw[:, :3, None] * (r[:, None] * u)[:, None, :])  # (n+1, 3, 3)
        self.rr = _prefix(r * r)

    def rss(self, lo: np.ndarray, k: np.ndarray, hi: np.ndarray, a_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(RSS of the local wander alone, RSS with the step) per candidate."""
        a = (np.asarray(a_s, float) - self.t0) / self.half
        mw = _recentre(self.uu[hi] - self.uu[lo], a, 5)  # (m, 5, 3, 3) Σ uuᵀ s^k over the window
        ma = _recentre(self.uu[hi] - self.uu[k], a, 3)  # … after the step
        rw = _recentre(self.ru[hi] - self.ru[lo], a, 3)  # (m, 3, 3) Σ r u s^k
        ra = self.ru[hi, 0] - self.ru[k, 0]
        m = len(a)
        g = np.zeros((m, 12, 12))
        for p in range(3):
            for q in range(3):
                g[:, 3 * p : 3 * p + 3, 3 * q : 3 * q + 3] = mw[:, p + q]
            g[:, 3 * p : 3 * p + 3, 9:] = ma[:, p]
            g[:, 9:, 3 * p : 3 * p + 3] = ma[:, p]
        g[:, 9:, 9:] = ma[:, 0]
        b = np.concatenate([rw.reshape(m, 9), ra], axis=1)
        rr = self.rr[hi] - self.rr[lo]
        return rr - _explained(g[:, :9, :9], b[:, :9]), rr - _explained(g, b)


def _prefix(a: np.ndarray) -> np.ndarray:
    return np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])


def _recentre(moments: np.ndarray, a: np.ndarray, count: int) -> np.ndarray:
    """Σ w (x − a)^k from Σ w x^j (j < ``count``), per candidate."""
    from math import comb

    out = np.zeros((len(a), count) + moments.shape[2:])
    shape = (-1,) + (1,) * (moments.ndim - 2)
    for k in range(count):
        for j in range(k + 1):
            out[:, k] += comb(k, j) * ((-a) ** (k - j)).reshape(shape) * moments[:, j]
    return out


def _explained(g: np.ndarray, b: np.ndarray) -> np.ndarray:
    """bᵀG⁺b per candidate: the square a least-squares fit explains (pseudo-inverse: a column
    the window cannot determine explains nothing)."""
    coef = np.einsum("mij,mj->mi", np.linalg.pinv(g, hermitian=True), b)
    return np.einsum("mi,mi->m", coef, b)


def shape_information(gram: np.ndarray, nuisance: int, var: float, sigma_max: float, min_unique: float) -> np.ndarray:
    """The information (per unit variance ``var``) a side's Gram matrix holds on its last
    columns (the shape terms) once its first ``nuisance`` (its offset) are fitted — the Schur
    complement — kept only along the directions that side determines, as
    ``magcal.diagnose.softiron.determined_directions`` judges them: pinned to ``sigma_max``
    (1σ) and keeping ``min_unique`` of their column's length once the offset is fitted (below
    that the shape trades with the offset along a flat valley, and a wandering offset would be
    read as a change of shape)."""
    a, b, c = gram[:nuisance, :nuisance], gram[:nuisance, nuisance:], gram[nuisance:, nuisance:]
    s = c - b.T @ np.linalg.pinv(a, hermitian=True) @ b
    lam, vec = np.linalg.eigh(0.5 * (s + s.T))
    share = lam / np.maximum(vec.T**2 @ np.diag(c), 1e-300)
    ok = (share >= min_unique**2) & (lam * sigma_max**2 >= max(var, 1e-300))
    return (vec[:, ok] * (lam[ok] / max(var, 1e-300))) @ vec[:, ok].T


def parallel_sum(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A(A + B)⁺B: the information on the difference of a quantity two independent sets of
    samples each measure (A, B their information) — nothing along a direction either set
    leaves free, and (A⁻¹ + B⁻¹)⁻¹ where both pin it."""
    p = a @ np.linalg.pinv(a + b, hermitian=True) @ b
    return 0.5 * (p + p.T)


def shared_directions(before: np.ndarray, after: np.ndarray, sigma_max: float) -> np.ndarray:
    """(6, k) orthonormal shape directions in which a change from ``before`` to ``after`` (the
    two sides' information on the shape terms along what each determines, ``shape_information``)
    is determined to √2 × ``sigma_max`` (1σ; each side pinning it to ``sigma_max``)."""
    lam, vec = np.linalg.eigh(parallel_sum(before, after))
    return vec[:, lam * 2.0 * sigma_max**2 >= 1.0 - 1e-9]
