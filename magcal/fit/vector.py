"""Fitting a calibration against the expected field vector (attitude + Earth model), or its
magnitude where a recording has no attitude — with an interference term (current, throttle)
kept only when held-out time blocks show it helps and it stands above its floor.

Model (body frame, µT), the same as ``magcal.core.calibration``::

    h = W (m − b − k·x)        W symmetric soft iron, b offset, k per unit of channel x

Vector mode (``expected_ut`` given) solves the forward model ``m = W⁻¹ h_expected + b + k·x``
(the sensor's noise is in m) by linear least squares, re-weighted (Huber) against outliers; this
pins offsets, soft iron and k even when the flight is mostly level, which the magnitude cannot.
Magnitude mode fits ``|W (m − b − k·x)| = F`` by robust non-linear least squares, F the Earth
model's magnitude when known; with too little rotation it falls back to W = s·I.

Unknown-field mode (``expected_ut`` an :class:`UnknownField`: the attitude but no position) fits
the Earth-frame field B as three more unknowns, ``m = W⁻¹ Rᵀ B + b + k·x`` with R the attitude
(body → NED): a field unknown but constant over the flight. W and B share one scale (W/s and
s·B predict the same m), fixed by det W = 1, so the field's size is the sensor's own reading of
it, not a measurement; the offset, the shape of W, k and the field's inclination are pinned by
the attitude's turns. B's horizontal direction is in the attitude's heading frame: it is the
declination only where the heading came from something other than this magnetometer.

Held-out judgement: the samples are cut into ``blocks`` contiguous time blocks; each is predicted
by a fit to the others. A term is kept when it lowers the held-out residual and its coefficient
differs from zero at p < 0.001 (χ², 3 dof, σ widened for correlated residuals). Its *floor* is
the size along the fitted direction at which that test would just report it (4.03 σ): a
coefficient below it cannot be told from none.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from ..core.calibration import Calibration
from . import tails
from .failure import FitFailure

MIN_SAMPLES = 60
HUBER_K = 1.345
P_KEEP = 1e-3
EARTH_FIELD_FORMAT = "magcal.earth_field/1"
SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass(frozen=True)
class UnknownField:
    """The expected field is Rᵀ B for an Earth-frame B fitted with the calibration: ``r_nb``
    (n, 3, 3), the attitude (body → NED) at each sample."""

    r_nb: np.ndarray

    def __getitem__(self, rows) -> "UnknownField":
        return UnknownField(self.r_nb[rows])

    def __len__(self) -> int:
        return len(self.r_nb)

    def body(self, b_ned) -> np.ndarray:
        """Rᵀ B per sample (n, 3)."""
        return np.einsum("nji,j->ni", self.r_nb, np.asarray(b_ned, np.float64))


def _w_from(p) -> np.ndarray:
    w = np.zeros((3, 3))
    for v, (i, j) in zip(p, SYM):
        w[i, j] = w[j, i] = v
    return w


@dataclass(frozen=True)
class Solve:
    """One fit: W, b, the per-term coefficients K (p, 3), the covariance of (b, K), the scale."""

    w: np.ndarray
    b: np.ndarray
    k: np.ndarray  # (p, 3), one row per term
    cov_bk: np.ndarray  # (3 + 3p, 3 + 3p)
    sigma_ut: float
    inflation: float
    model: str
    earth_ned_ut: np.ndarray | None = None  # unknown-field mode: the fitted B (NED, µT)
    cov_earth: np.ndarray | None = None  # its 3×3 covariance


def _design(m, x) -> np.ndarray:
    """Rows of A m + c + Σ d_j x_j (A symmetric) for the parameters (A6, c3, d1 3, d2 3 …), axis by axis."""
    n, p = len(m), x.shape[1]
    a = np.zeros((n, 3, 9 + 3 * p))
    for col, (i, j) in enumerate(SYM):
        a[:, i, col] += m[:, j]
        if i != j:
            a[:, j, col] += m[:, i]
    for i in range(3):
        a[:, i, 6 + i] = 1.0
        for t in range(p):
            a[:, i, 9 + 3 * t + i] = x[:, t]
    return a.reshape(3 * n, 9 + 3 * p)


def _inflation(res: np.ndarray) -> float:
    """(1 + ρ)/(1 − ρ) from the lag-1 autocorrelation of the residuals (≥ 1)."""
    r = res - res.mean(axis=0)
    num = float(np.sum(r[1:] * r[:-1]))
    den = float(np.sum(r * r)) or 1.0
    rho = min(max(num / den, 0.0), 0.95)
    return (1 + rho) / (1 - rho)


def _conditioning(jtj: np.ndarray) -> float:
    """Condition number of a normal matrix with its columns scaled to unit diagonal."""
    d = np.sqrt(np.maximum(np.diag(jtj), 1e-300))
    return float(np.linalg.cond(jtj / np.outer(d, d)))


def _weighted_solve(a, y, w) -> np.ndarray:
    """Weighted least squares by the normal equations, columns scaled to unit diagonal (a few
    dozen unknowns over thousands of rows: far cheaper than an SVD of the tall matrix)."""
    aw = a * w[:, None]
    ata, aty = aw.T @ a, aw.T @ y
    d = np.sqrt(np.maximum(np.diag(ata), 1e-300))
    return np.linalg.lstsq(ata / np.outer(d, d), aty / d, rcond=None)[0] / d


def solve_vector(m, x, expected, iterations: int = 8) -> Solve | FitFailure:
    """Robust linear least squares of the forward model m = A h + b + K x (A = W⁻¹ symmetric,
    x (n, p) with p ≥ 0 terms): the sensor's noise is in m, so m is the response."""
    a, y = _design(expected, x), m.reshape(-1)
    wts = np.ones(len(m))
    for _ in range(iterations):
        theta = _weighted_solve(a, y, np.repeat(wts, 3))
        res = (y - a @ theta).reshape(-1, 3)
        norm = np.linalg.norm(res, axis=1)
        scale = 1.4826 * np.median(norm) / np.sqrt(2.0) or 1e-9  # per-axis σ from the 3-D residual
        wts = np.minimum(1.0, HUBER_K * scale * np.sqrt(3) / np.maximum(norm, 1e-12))
    ata = (a * np.repeat(wts, 3)[:, None]).T @ a
    if _conditioning(ata) > 1e10:
        return FitFailure("ill_conditioned", "the attitude, field and channels vary too little to pin the calibration")
    infl = _inflation(res)
    sigma = float(np.sqrt(np.sum(np.repeat(wts, 3) * res.reshape(-1) ** 2) / max(1, len(y) - a.shape[1])))
    cov = np.linalg.inv(ata) * sigma**2 * infl
    inv_w = _w_from(theta[:6])
    if np.any(np.linalg.eigvalsh(inv_w) <= 0):
        return FitFailure("not_positive_definite", "the fitted soft iron is not positive definite")
    return Solve(np.linalg.inv(inv_w), theta[6:9], theta[9:].reshape(-1, 3), cov[6:, 6:], sigma, infl, "vector")


def _attitude_start(m, uf: UnknownField) -> np.ndarray:
    """B from R m = B + R b (W taken as I, no term): linear in (B, b), the classic start."""
    a = np.concatenate([np.broadcast_to(np.eye(3), uf.r_nb.shape), uf.r_nb], axis=2).reshape(-1, 6)
    y = np.einsum("nij,nj->ni", uf.r_nb, m).reshape(-1)
    return np.linalg.lstsq(a, y, rcond=None)[0][:3]


def _joint_design(lin, b_ned, x, uf: UnknownField) -> tuple[np.ndarray, np.ndarray]:
    """(Jacobian of the prediction in (A6, b, K, B), the linear part's design at this B)."""
    a_lin = _design(uf.body(b_ned), x)
    a_b = np.einsum("ij,nkj->nik", _w_from(lin[:6]), uf.r_nb).reshape(-1, 3)  # ∂(A Rᵀ B)/∂B = A Rᵀ
    return np.hstack([a_lin, a_b]), a_lin


def _gauge(lin, b_ned) -> np.ndarray:
    """The direction that changes nothing: A·(1 + ε) with B·(1 − ε), as a unit vector."""
    g = np.concatenate([lin[:6], np.zeros(len(lin) - 6), -b_ned])
    return g / np.linalg.norm(g)


def _det_one(lin, b_ned) -> tuple[np.ndarray, np.ndarray] | None:
    """Move along the gauge to det A = 1 (det W = 1): the sensor's own mean gain; None where A
    is no gain at all (det ≤ 0 or not finite: the solve has turned the field inside out)."""
    det = float(np.linalg.det(_w_from(lin[:6])))
    if not (np.isfinite(det) and det > 0.0) or not np.all(np.isfinite(b_ned)):
        return None
    s = det ** (1.0 / 3.0)
    out = lin.copy()
    out[:6] /= s
    return out, b_ned * s


def _huber(res) -> tuple[np.ndarray, np.ndarray]:
    """(per-sample Huber weights, repeated per axis) from (n, 3) residuals, as ``solve_vector``."""
    norm = np.linalg.norm(res, axis=1)
    scale = 1.4826 * np.median(norm) / np.sqrt(2.0) or 1e-9
    w = np.minimum(1.0, HUBER_K * scale * np.sqrt(3) / np.maximum(norm, 1e-12))
    return w, np.repeat(w, 3)


def solve_unknown_field(m, x, uf: UnknownField, iterations: int = 12) -> Solve | FitFailure:
    """Robust Gauss–Newton of m = A Rᵀ B + b + K x with B (NED) unknown and constant, from the
    attitude start; the scale A and B share is fixed at det A = 1 (see the module docstring)."""
    b_ned = _attitude_start(m, uf)
    first = solve_vector(m, x, uf.body(b_ned))
    if not first:
        return first
    lin = np.concatenate([np.linalg.inv(first.w)[[i for i, _ in SYM], [j for _, j in SYM]], first.b, first.k.reshape(-1)])
    moved = _det_one(lin, b_ned)
    y, wts3 = m.reshape(-1), np.ones(3 * len(m))
    for _ in range(iterations):
        if moved is None:
            break
        lin, b_ned = moved
        jac, a_lin = _joint_design(lin, b_ned, x, uf)
        res = y - a_lin @ lin
        wts, wts3 = _huber(res.reshape(-1, 3))
        g = _gauge(lin, b_ned)
        ata = (jac * wts3[:, None]).T @ jac
        step = np.linalg.solve(ata + np.trace(ata) / len(g) * np.outer(g, g), (jac * wts3[:, None]).T @ res)
        moved = _det_one(lin + step[:-3], b_ned + step[-3:])
        if moved is not None and np.max(np.abs(step)) < 1e-9 * (1.0 + np.max(np.abs(moved[0]))):
            break
    if moved is None:
        return FitFailure("not_positive_definite", "against an unknown constant field the fitted soft iron "
                          "is no gain (its determinant is not positive): the attitude does not pin it")
    return _unknown_solve(m, x, uf, *moved)


def _unknown_solve(m, x, uf: UnknownField, lin, b_ned) -> Solve | FitFailure:
    """The Solve at a converged (A, b, K, B): σ from the joint normal matrix (the gauge removed:
    b, K and B's direction do not depend on it)."""
    jac, a_lin = _joint_design(lin, b_ned, x, uf)
    y = m.reshape(-1)
    res = (y - a_lin @ lin).reshape(-1, 3)
    _, wts3 = _huber(res)
    ata = (jac * wts3[:, None]).T @ jac
    g = _gauge(lin, b_ned)
    if _conditioning(ata + np.trace(ata) / len(g) * np.outer(g, g)) > 1e10:
        return FitFailure("ill_conditioned", "the attitude turned too little to pin the calibration and an unknown "
                                             "Earth field together")
    infl = _inflation(res)
    sigma = float(np.sqrt(np.sum(wts3 * res.reshape(-1) ** 2) / max(1, len(y) - jac.shape[1] + 1)))
    cov = np.linalg.pinv(ata, hermitian=True) * sigma**2 * infl
    inv_w = _w_from(lin[:6])
    if np.any(np.linalg.eigvalsh(inv_w) <= 0):
        return FitFailure("not_positive_definite", "the fitted soft iron is not positive definite")
    return Solve(np.linalg.inv(inv_w), lin[6:9], lin[9:].reshape(-1, 3), cov[6:-3, 6:-3], sigma, infl, "vector",
                 earth_ned_ut=b_ned, cov_earth=cov[-3:, -3:])


def _unpack(p, full_w: bool, nterms: int):
    w = _w_from(p[:6]) if full_w else np.eye(3) * p[0]
    o = 6 if full_w else 1
    return w, p[o:o + 3], p[o + 3:o + 3 + 3 * nterms].reshape(nterms, 3)


def _mag_fun_jac(p, m, x, f, full_w: bool):
    """Residuals |W d| − f, d = m − b − x K, and their analytic Jacobian."""
    w, b, k = _unpack(p, full_w, x.shape[1])
    d = m - b - x @ k
    h = d @ w.T
    nh = np.maximum(np.linalg.norm(h, axis=1), 1e-12)
    u = h / nh[:, None]
    wu = u @ w  # W symmetric: ∂|Wd|/∂d = Wᵀu
    if full_w:
        cols = [u[:, i] * d[:, j] + (u[:, j] * d[:, i] if i != j else 0.0) for i, j in SYM]
    else:
        cols = [np.sum(u * d, axis=1)]
    jac = np.column_stack(cols + [-wu[:, i] for i in range(3)]
                          + [-x[:, t] * wu[:, i] for t in range(x.shape[1]) for i in range(3)])
    return nh - f, jac


def solve_magnitude(m, x, field_ut: float, full_w: bool = True) -> Solve | FitFailure:
    """Robust fit of |W (m − b − x K)| = field_ut; W = s·I when ``full_w`` is False."""
    b0 = np.median(m, axis=0)
    s0 = field_ut / max(float(np.median(np.linalg.norm(m - b0, axis=1))), 1e-9)
    p0 = np.concatenate([[s0, 0, 0, s0, 0, s0] if full_w else [s0], b0, np.zeros(3 * x.shape[1])])
    sol = optimize.least_squares(lambda q: _mag_fun_jac(q, m, x, field_ut, full_w)[0], p0,
                                 jac=lambda q: _mag_fun_jac(q, m, x, field_ut, full_w)[1],
                                 loss="huber", f_scale=max(0.02 * field_ut, 1e-6), x_scale="jac", max_nfev=200)
    jtj = sol.jac.T @ sol.jac
    if not sol.success or _conditioning(jtj) > 1e8:
        if full_w:
            return solve_magnitude(m, x, field_ut, full_w=False)
        return FitFailure("ill_conditioned", "the field magnitude alone does not pin this calibration")
    w, b, k = _unpack(sol.x, full_w, x.shape[1])
    if np.any(np.linalg.eigvalsh(w) <= 0):
        return FitFailure("not_positive_definite", "the fitted soft iron is not positive definite")
    res = sol.fun
    infl = _inflation(res[:, None])
    sigma = float(1.4826 * np.median(np.abs(res - np.median(res))))
    o = 6 if full_w else 1
    cov = (np.linalg.pinv(jtj) * sigma**2 * infl)[o:, o:]
    return Solve(w, b, k, cov, sigma, infl, "magnitude" if full_w else "magnitude-sphere")


def residuals(s: Solve, m, x, expected=None, field_ut=None) -> tuple[np.ndarray | None, np.ndarray]:
    """(vector residual (n, 3) or None, magnitude residual (n,)) of a solve on samples."""
    h = (m - s.b - x @ s.k) @ s.w.T
    if isinstance(expected, UnknownField):
        expected = expected.body(s.earth_ned_ut)
    vec = None if expected is None else h - expected
    f = np.linalg.norm(expected, axis=1) if expected is not None else field_ut
    return vec, np.linalg.norm(h, axis=1) - f


def _solve(m, x, expected, field_ut):
    if isinstance(expected, UnknownField):
        return solve_unknown_field(m, x, expected)
    if expected is not None:
        return solve_vector(m, x, expected)
    return solve_magnitude(m, x, field_ut)


def heldout(m, x, expected, field_ut, blocks: int) -> dict:
    """Mean over contiguous time blocks of the RMS residual when each is left out of the fit."""
    edges = np.linspace(0, len(m), blocks + 1).round().astype(int)
    vec, mag = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        train = np.ones(len(m), bool)
        train[lo:hi] = False
        s = _solve(m[train], x[train], None if expected is None else expected[train], field_ut)
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
    """A calibration fitted against the expected field, with the decision on each term."""

    mode: str  # "vector", "magnitude" or "magnitude-sphere"
    calibration: Calibration
    sigma_offset_ut: np.ndarray
    terms: tuple[dict, ...]  # per candidate: channel, role, kept, coefficient, σ, floor, p, held-out
    heldout: dict
    rms_ut: float
    n_used: int
    autocorrelation_factor: float
    warnings: tuple[str, ...] = field(default_factory=tuple)
    earth_field: dict | None = None  # unknown-field mode: ``earth_field_summary``

    def __bool__(self) -> bool:
        return True

    def interference_term(self) -> str | None:
        """The kept term an autopilot can apply (current or throttle), if any."""
        return next((t["channel"] for t in self.terms if t["kept"] and t["role"] == "interference"), None)

    def to_dict(self) -> dict:
        return {
            "format": "magcal.fit.vector/1",
            "mode": self.mode,
            "calibration": self.calibration.to_dict(),
            "uncertainty": {"offset_ut": [float(v) for v in self.sigma_offset_ut],
                            "autocorrelation_factor": self.autocorrelation_factor},
            "terms": list(self.terms),
            "heldout": self.heldout,
            "rms_ut": self.rms_ut,
            "n_used": self.n_used,
            "warnings": list(self.warnings),
            **({"earth_field": self.earth_field} if self.earth_field else {}),
        }


def _term_stats(s: Solve, j: int) -> dict:
    """Coefficient of term j, its σ, the χ²(3) p-value against zero, and its floor: the size
    along the fitted direction at which the χ² test at P_KEEP would just report it."""
    k, cov = s.k[j], s.cov_bk[3 + 3 * j: 6 + 3 * j, 3 + 3 * j: 6 + 3 * j]
    norm = float(np.linalg.norm(k))
    u = k / norm if norm > 0 else np.array([1.0, 0.0, 0.0])
    chi2 = float(k @ np.linalg.pinv(cov) @ k)
    reach = float(np.sqrt(tails.chi2_isf(P_KEEP, 3)))  # 4.03σ: where the keep test starts to report
    return {"coef_ut_per_unit": [float(v) for v in k], "sigma_ut_per_unit": [float(v) for v in np.sqrt(np.diag(cov))],
            "norm_ut_per_unit": norm, "floor_ut_per_unit": float(reach * np.sqrt(max(u @ cov @ u, 0.0))),
            "p_value": float(tails.chi2_sf(chi2, 3))}


def choose_term(channels: dict, candidates=("current_a", "throttle")) -> str | None:
    """The first candidate channel that varies (an interference term needs something to follow)."""
    for name in candidates:
        v = channels.get(name)
        if v is not None and np.all(np.isfinite(v)) and np.std(v) > 0:
            return name
    return None


def motors_on(channels: dict, min_fraction: float = 0.05) -> np.ndarray | None:
    """1 where the motors run (throttle above 2 %, else any motor output above its idle), or None
    when the recording does not hold both states for at least ``min_fraction`` of its samples."""
    if "throttle" in channels:
        on = np.asarray(channels["throttle"]) > 0.02
    else:
        motors = [np.asarray(v) for k, v in channels.items() if k.startswith("motor") and k[5:].isdigit()]
        if not motors:
            return None
        on = np.zeros(len(motors[0]), bool)
        for v in motors:
            lo, hi = np.percentile(v, 1), np.percentile(v, 99)
            on |= v > lo + 0.05 * (hi - lo) if hi > lo else False
    frac = float(on.mean())
    return on.astype(np.float64) if min_fraction <= frac <= 1 - min_fraction else None


def _columns(names, cols, n) -> np.ndarray:
    return np.column_stack([cols[c] for c in names]) if names else np.zeros((n, 0))


def _judge(names, j, cols, m, exp, f, blocks, ho, base_key) -> tuple[dict, Solve | FitFailure]:
    """Fit with ``names`` (term j the one judged) and say whether it earns its place."""
    key = "rms_vector_ut" if exp is not None else "rms_magnitude_ut"
    x = _columns(names, cols, len(m))
    label = "+".join(names)
    ho[label] = heldout(m, x, exp, f, blocks)
    s = _solve(m, x, exp, f)
    info = {"channel": names[j], "kept": False, "heldout_model": label}
    if s:
        info.update(_term_stats(s, j))
        falls = ho[label].get(key, np.inf) < ho[base_key].get(key, np.inf)
        info["heldout_falls"] = bool(falls)
        info["kept"] = bool(falls and info["p_value"] < P_KEEP)
    return info, s


def fit_vector(field_ut, channels: dict, expected_ut=None, earth_field_ut: float | None = None,
               term: str | None = "auto", blocks: int = 5, step: bool = True) -> VectorFit | FitFailure:
    """Fit (m, channels) against ``expected_ut`` (n, 3) — or |m| against ``earth_field_ut`` when
    there is no expected vector; an :class:`UnknownField` (the attitude, no position) fits the
    Earth-frame field too. ``term``: "auto" (current, else throttle), None, or a channel.
    A motors-running step is judged first as a nuisance term, so that the current term is
    pinned by how the field follows the current, not by the jump between ground and air
    (``step=False`` leaves the step out, as tools with only a linear term do)."""
    m = np.asarray(field_ut, np.float64)
    ok = np.all(np.isfinite(m), axis=1)
    unknown = isinstance(expected_ut, UnknownField)
    if expected_ut is not None:
        ok &= np.all(np.isfinite(expected_ut.r_nb if unknown else expected_ut).reshape(len(m), -1), axis=1)
    if ok.sum() < MIN_SAMPLES:
        return FitFailure("too_few_samples", f"{int(ok.sum())} usable samples, at least {MIN_SAMPLES} needed")
    name = choose_term(channels) if term == "auto" else term
    if name is not None and name not in channels:
        return FitFailure("no_channel", f"no channel {name!r} to fit an interference term to")
    m, exp = m[ok], None if expected_ut is None else (expected_ut if unknown else np.asarray(expected_ut, np.float64))[ok]
    cols = {k: np.asarray(v, np.float64)[ok] for k, v in channels.items() if k == name}
    step = motors_on({k: np.asarray(v)[ok] for k, v in channels.items()}) if step else None
    if step is not None and name != "throttle":
        cols["motors_on"] = step
    f = earth_field_ut if earth_field_ut else float(np.median(np.linalg.norm(m - np.median(m, axis=0), axis=1)))
    ho = {"blocks": blocks, "none": heldout(m, np.zeros((len(m), 0)), exp, f, blocks)}
    chosen, base, terms = _solve(m, np.zeros((len(m), 0)), exp, f), [], []
    if not chosen:
        return chosen
    if "motors_on" in cols:
        info, s = _judge(["motors_on"], 0, cols, m, exp, f, blocks, ho, "none")
        terms.append({"role": "nuisance", **info})
        if info["kept"]:
            chosen, base = s, ["motors_on"]
    if name is not None:
        info, s = _judge(base + [name], len(base), cols, m, exp, f, blocks, ho, "+".join(base) or "none")
        terms.append({"role": "interference", **info})
        if info["kept"]:
            chosen, base = s, base + [name]
    ho["chosen"] = "+".join(base) or "none"
    return _result(chosen, base, tuple(terms), ho, m, _columns(base, cols, len(m)), exp, f)


def _result(s: Solve, names, terms, ho, m, x, exp, f) -> VectorFit:
    if s.earth_ned_ut is not None:
        f = float(np.linalg.norm(s.earth_ned_ut))  # det W = 1: the field as the sensor's mean gain reads it
    cal = Calibration(offset_ut=s.b, field_ut=f, soft_iron=s.w,
                      coef_ut_per_unit={n: s.k[j] for j, n in enumerate(names)}, reference={n: 0.0 for n in names})
    rv, rm = residuals(s, m, x, exp, f)
    rms = float(np.sqrt(np.mean(np.sum(rv**2, axis=1)))) if rv is not None else float(np.sqrt(np.mean(rm**2)))
    warnings = ()
    if s.model == "magnitude-sphere":
        warnings = ("the recording turned too little to fit soft iron from |m| alone: a sphere was fitted",)
    return VectorFit(mode=s.model, calibration=cal, sigma_offset_ut=np.sqrt(np.diag(s.cov_bk)[:3]), terms=terms,
                     heldout=ho, rms_ut=rms, n_used=len(m), autocorrelation_factor=float(s.inflation),
                     warnings=warnings, earth_field=earth_field_summary(s))


def _angles_deg(b_ned) -> np.ndarray:
    """(inclination, heading-frame declination) of an NED vector, degrees."""
    n, e, d = b_ned
    return np.degrees([np.arctan2(d, np.hypot(n, e)), np.arctan2(e, n)])


def earth_field_summary(s: Solve) -> dict | None:
    """What an unknown-field fit found of the Earth's field and what it cannot say (None for a
    fit against a known field). The angles are scale-free, so their σ (first order, numerical
    gradient) do not depend on the det W = 1 convention; the size does, and is not stated."""
    if s.earth_ned_ut is None:
        return None
    b, cov = np.asarray(s.earth_ned_ut, np.float64), np.asarray(s.cov_earth, np.float64)
    eps = 1e-6 * np.linalg.norm(b)
    grad = np.column_stack([(_angles_deg(b + eps * e) - _angles_deg(b - eps * e)) / (2 * eps) for e in np.eye(3)])
    inc, dec = _angles_deg(b)
    s_inc, s_dec = np.sqrt(np.clip(np.diag(grad @ cov @ grad.T), 0.0, None))
    return {"format": EARTH_FIELD_FORMAT, "mode": "unknown_constant", "ned_ut": [float(v) for v in b],
            "size_ut": float(np.linalg.norm(b)), "size_determined": False,
            "inclination_deg": float(inc), "sigma_inclination_deg": float(s_inc),
            "heading_frame_declination_deg": float(dec), "sigma_heading_frame_declination_deg": float(s_dec),
            "declination_determined": False}
