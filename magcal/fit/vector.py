"""Fitting a calibration against the expected field vector (attitude + Earth model), or its
magnitude where a recording has no attitude — with an interference term (current, throttle)
kept only when held-out time blocks show it helps and it stands above its floor.

Model (body frame, µT), the same as ``magcal.core.calibration``::

    h = W (m − b − k·x)        W symmetric soft iron, b offset, k per unit of channel x

Vector mode (``expected_ut`` given) solves ``W m + c + d·x = h_expected`` for the 12 numbers
(W, c = −W b, d = −W k) by linear least squares, re-weighted (Huber) against outliers; this pins
offsets, soft iron and k even when the flight is mostly level, which the magnitude cannot.
Magnitude mode fits ``|W (m − b − k·x)| = F`` by robust non-linear least squares, F the Earth
model's magnitude when known; with too little rotation it falls back to W = s·I.

Held-out judgement: the samples are cut into ``blocks`` contiguous time blocks; each is predicted
by a fit to the others. A term is kept when it lowers the held-out residual and its coefficient
differs from zero at p < 0.001 (χ², 3 dof, σ widened for correlated residuals). Its *floor* is
three σ along the fitted direction: a coefficient below it cannot be told from none.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from ..core.calibration import Calibration
from .failure import FitFailure

MIN_SAMPLES = 60
HUBER_K = 1.345
P_KEEP = 1e-3
SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _w_from(p) -> np.ndarray:
    w = np.zeros((3, 3))
    for v, (i, j) in zip(p, SYM):
        w[i, j] = w[j, i] = v
    return w


@dataclass(frozen=True)
class Solve:
    """One fit: W, b, k (zeros when no term), their covariance, the residual scale."""

    w: np.ndarray
    b: np.ndarray
    k: np.ndarray
    cov_bk: np.ndarray  # (6, 6) for (b, k)
    sigma_ut: float
    inflation: float
    model: str


def _design(m, x) -> np.ndarray:
    """Rows of W m + c + d x for the parameter vector (W6, c3, d3), stacked axis by axis."""
    n = len(m)
    a = np.zeros((n, 3, 12))
    for col, (i, j) in enumerate(SYM):
        a[:, i, col] += m[:, j]
        if i != j:
            a[:, j, col] += m[:, i]
    for i in range(3):
        a[:, i, 6 + i] = 1.0
        a[:, i, 9 + i] = x
    return a.reshape(3 * n, 12)


def _inflation(res: np.ndarray) -> float:
    """(1 + ρ)/(1 − ρ) from the lag-1 autocorrelation of the residuals (≥ 1)."""
    r = res - res.mean(axis=0)
    num = float(np.sum(r[1:] * r[:-1]))
    den = float(np.sum(r * r)) or 1.0
    rho = min(max(num / den, 0.0), 0.95)
    return (1 + rho) / (1 - rho)


def _bk(theta: np.ndarray) -> np.ndarray:
    w = _w_from(theta[:6])
    return np.concatenate([-np.linalg.solve(w, theta[6:9]), -np.linalg.solve(w, theta[9:12])])


def _propagate(theta, cov_theta, f) -> np.ndarray:
    """Covariance of f(θ) by a numerical Jacobian."""
    base = f(theta)
    jac = np.zeros((len(base), len(theta)))
    for i in range(len(theta)):
        h = 1e-6 * max(1.0, abs(theta[i]))
        t = theta.copy()
        t[i] += h
        jac[:, i] = (f(t) - base) / h
    return jac @ cov_theta @ jac.T


def solve_vector(m, x, expected, use_term: bool, iterations: int = 8) -> Solve | FitFailure:
    a = _design(m, x)
    if not use_term:
        a = a[:, :9]
    y = expected.reshape(-1)
    wts = np.ones(len(m))
    for _ in range(iterations):
        sw = np.repeat(np.sqrt(wts), 3)
        theta, *_ = np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)
        res = (y - a @ theta).reshape(-1, 3)
        norm = np.linalg.norm(res, axis=1)
        scale = 1.4826 * np.median(norm) / np.sqrt(2.0) or 1e-9  # per-axis σ from the 3-D residual
        wts = np.minimum(1.0, HUBER_K * scale * np.sqrt(3) / np.maximum(norm, 1e-12))
    ata = (a * np.repeat(wts, 3)[:, None]).T @ a
    if np.linalg.cond(ata) > 1e12:
        return FitFailure("ill_conditioned", "the attitude and field vary too little to pin the calibration")
    infl = _inflation(res)
    sigma = float(np.sqrt(np.sum(np.repeat(wts, 3) * res.reshape(-1) ** 2) / max(1, len(y) - a.shape[1])))
    cov = np.linalg.inv(ata) * sigma**2 * infl
    full = np.concatenate([theta, np.zeros(12 - len(theta))])
    cov_full = np.zeros((12, 12))
    cov_full[: len(theta), : len(theta)] = cov
    w = _w_from(full[:6])
    if np.any(np.linalg.eigvalsh(w) <= 0):
        return FitFailure("not_positive_definite", "the fitted soft iron is not positive definite")
    bk = _bk(full)
    return Solve(w, bk[:3], bk[3:], _propagate(full, cov_full, _bk), sigma, infl, "vector")


def _mag_residual(p, m, x, f, full_w: bool):
    w = _w_from(p[:6]) if full_w else np.eye(3) * p[0]
    o = 6 if full_w else 1
    b, k = p[o:o + 3], p[o + 3:o + 6]
    return np.linalg.norm((m - b - np.outer(x, k)) @ w.T, axis=1) - f


def solve_magnitude(m, x, field_ut: float, use_term: bool, full_w: bool = True) -> Solve | FitFailure:
    """Robust fit of |W (m − b − k x)| = field_ut; W = s·I when ``full_w`` is False."""
    b0 = np.median(m, axis=0)
    s0 = field_ut / max(float(np.median(np.linalg.norm(m - b0, axis=1))), 1e-9)
    p0 = np.concatenate([[s0, 0, 0, s0, 0, s0] if full_w else [s0], b0, np.zeros(3)])
    mask = np.ones(len(p0), bool)
    if not use_term:
        mask[-3:] = False

    def fun(q):
        p = p0.copy()
        p[mask] = q
        return _mag_residual(p, m, x, field_ut, full_w)

    scale = max(0.05 * field_ut, 1e-6)
    sol = optimize.least_squares(fun, p0[mask], loss="huber", f_scale=scale, x_scale="jac", max_nfev=400)
    res = sol.fun
    jtj = sol.jac.T @ sol.jac
    if not sol.success or np.linalg.cond(jtj) > 1e10:
        if full_w:
            return solve_magnitude(m, x, field_ut, use_term, full_w=False)
        return FitFailure("ill_conditioned", "the field magnitude alone does not pin this calibration")
    p = p0.copy()
    p[mask] = sol.x
    o = 6 if full_w else 1
    w = _w_from(p[:6]) if full_w else np.eye(3) * p[0]
    if np.any(np.linalg.eigvalsh(w) <= 0):
        return FitFailure("not_positive_definite", "the fitted soft iron is not positive definite")
    infl = _inflation(res[:, None])
    sigma = float(1.4826 * np.median(np.abs(res - np.median(res))))
    cov = np.linalg.pinv(jtj) * sigma**2 * infl
    idx = np.flatnonzero(mask)
    cov_bk = np.zeros((6, 6))
    sel = [list(idx).index(i) if i in idx else None for i in range(o, o + 6)]
    for r, sr in enumerate(sel):
        for c, sc in enumerate(sel):
            if sr is not None and sc is not None:
                cov_bk[r, c] = cov[sr, sc]
    return Solve(w, p[o:o + 3], p[o + 3:o + 6], cov_bk, sigma, infl, "magnitude" if full_w else "magnitude-sphere")


def residuals(s: Solve, m, x, expected=None, field_ut=None) -> tuple[np.ndarray | None, np.ndarray]:
    """(vector residual (n, 3) or None, magnitude residual (n,)) of a solve on samples."""
    h = (m - s.b - np.outer(x, s.k)) @ s.w.T
    vec = None if expected is None else h - expected
    f = np.linalg.norm(expected, axis=1) if expected is not None else field_ut
    return vec, np.linalg.norm(h, axis=1) - f


def _solve(m, x, expected, field_ut, use_term):
    if expected is not None:
        return solve_vector(m, x, expected, use_term)
    return solve_magnitude(m, x, field_ut, use_term)


def heldout(m, x, expected, field_ut, use_term: bool, blocks: int) -> dict:
    """Mean over contiguous time blocks of the RMS residual when each is left out of the fit."""
    edges = np.linspace(0, len(m), blocks + 1).round().astype(int)
    vec, mag = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        train = np.ones(len(m), bool)
        train[lo:hi] = False
        s = _solve(m[train], x[train], None if expected is None else expected[train], field_ut, use_term)
        if not s:
            return {"failure": s.reason}
        rv, rm = residuals(s, m[~train], x[~train], None if expected is None else expected[~train], field_ut)
        if rv is not None:
            vec.append(float(np.sqrt(np.mean(np.sum(rv**2, axis=1)))))
        mag.append(float(np.sqrt(np.mean(rm**2))))
    out = {"rms_magnitude_ut": float(np.mean(mag)), "per_block_magnitude_ut": mag}
    if vec:
        out.update(rms_vector_ut=float(np.mean(vec)), per_block_vector_ut=vec)
    return out


@dataclass(frozen=True)
class VectorFit:
    """A calibration fitted against the expected field, with the interference-term decision."""

    mode: str  # "vector", "magnitude" or "magnitude-sphere"
    calibration: Calibration
    sigma_offset_ut: np.ndarray
    term: dict  # channel, kept, coefficient, σ, floor, p, held-out residuals with and without
    heldout: dict
    rms_ut: float
    n_used: int
    autocorrelation_factor: float
    warnings: tuple[str, ...] = field(default_factory=tuple)

    def __bool__(self) -> bool:
        return True

    def to_dict(self) -> dict:
        return {
            "format": "magcal.fit.vector/1",
            "mode": self.mode,
            "calibration": self.calibration.to_dict(),
            "uncertainty": {"offset_ut": [float(v) for v in self.sigma_offset_ut],
                            "autocorrelation_factor": self.autocorrelation_factor},
            "term": self.term,
            "heldout": self.heldout,
            "rms_ut": self.rms_ut,
            "n_used": self.n_used,
            "warnings": list(self.warnings),
        }


def _term_stats(s: Solve) -> dict:
    k, cov = s.k, s.cov_bk[3:, 3:]
    norm = float(np.linalg.norm(k))
    u = k / norm if norm > 0 else np.array([1.0, 0.0, 0.0])
    chi2 = float(k @ np.linalg.pinv(cov) @ k)
    return {"coef_ut_per_unit": [float(v) for v in k], "sigma_ut_per_unit": [float(v) for v in np.sqrt(np.diag(cov))],
            "norm_ut_per_unit": norm, "floor_ut_per_unit": float(3 * np.sqrt(max(u @ cov @ u, 0.0))),
            "p_value": float(stats.chi2.sf(chi2, 3))}


def choose_term(channels: dict, candidates=("current_a", "throttle")) -> str | None:
    """The first candidate channel that varies (an interference term needs something to follow)."""
    for name in candidates:
        v = channels.get(name)
        if v is not None and np.all(np.isfinite(v)) and np.std(v) > 0:
            return name
    return None


def fit_vector(field_ut, channels: dict, expected_ut=None, earth_field_ut: float | None = None,
               term: str | None = "auto", blocks: int = 5) -> VectorFit | FitFailure:
    """Fit (m, channels) against ``expected_ut`` (n, 3) — or |m| against ``earth_field_ut`` when
    there is no expected vector. ``term``: "auto" (current, else throttle), None, or a channel."""
    m = np.asarray(field_ut, np.float64)
    ok = np.all(np.isfinite(m), axis=1) & (True if expected_ut is None else np.all(np.isfinite(expected_ut), axis=1))
    if ok.sum() < MIN_SAMPLES:
        return FitFailure("too_few_samples", f"{int(ok.sum())} usable samples, at least {MIN_SAMPLES} needed")
    name = choose_term(channels) if term == "auto" else term
    if name is not None and name not in channels:
        return FitFailure("no_channel", f"no channel {name!r} to fit an interference term to")
    m = m[ok]
    exp = None if expected_ut is None else np.asarray(expected_ut, np.float64)[ok]
    x = np.zeros(len(m)) if name is None else np.asarray(channels[name], np.float64)[ok]
    f = earth_field_ut if earth_field_ut else float(np.median(np.linalg.norm(m - np.median(m, axis=0), axis=1)))
    key = "rms_vector_ut" if exp is not None else "rms_magnitude_ut"
    ho = {"blocks": blocks, "without_term": heldout(m, x, exp, f, False, blocks)}
    base = _solve(m, x, exp, f, False)
    if not base:
        return base
    chosen, info = base, {"channel": name, "kept": False}
    if name is not None:
        ho["with_term"] = heldout(m, x, exp, f, True, blocks)
        with_term = _solve(m, x, exp, f, True)
        if with_term:
            info.update(_term_stats(with_term))
            falls = ho["with_term"].get(key, np.inf) < ho["without_term"].get(key, np.inf)
            info["heldout_falls"] = bool(falls)
            info["kept"] = bool(falls and info["p_value"] < P_KEEP)
            chosen = with_term if info["kept"] else base
    return _result(chosen, name if info["kept"] else None, info, ho, m, x, exp, f)


def _result(s: Solve, name, info, ho, m, x, exp, f) -> VectorFit:
    cal = Calibration(offset_ut=s.b, field_ut=f, soft_iron=s.w,
                      coef_ut_per_unit={name: s.k} if name else {}, reference={name: 0.0} if name else {})
    rv, rm = residuals(s, m, x, exp, f)
    rms = float(np.sqrt(np.mean(np.sum(rv**2, axis=1)))) if rv is not None else float(np.sqrt(np.mean(rm**2)))
    warnings = ()
    if s.model == "magnitude-sphere":
        warnings = ("the recording turned too little to fit soft iron from |m| alone: a sphere was fitted",)
    return VectorFit(mode=s.model, calibration=cal, sigma_offset_ut=np.sqrt(np.diag(s.cov_bk)[:3]), term=info,
                     heldout=ho, rms_ut=rms, n_used=len(m), autocorrelation_factor=float(s.inflation),
                     warnings=warnings)
