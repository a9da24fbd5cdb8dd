"""The geometric (maximum-likelihood) residual shared by the sphere and ellipsoid fits.

Model: h_i = W (m_i − b) has length r, so the residual of sample i is

    e_i = |W (m_i − b)| − r        (µT; Gaussian isotropic noise → least squares = ML)

W = expm(S) with S symmetric and trace S = 0, so W is symmetric positive definite with det W = 1
for every parameter value — the fit can never produce a non-PD matrix, and the overall scale,
which magnitudes cannot separate from |h|, sits in r alone. Parameter vector θ:

    kind "sphere"   : [b (3), r]                               S = 0
    kind "diagonal" : [b (3), r, s_xx, s_yy]                   S = diag(s_xx, s_yy, −s_xx−s_yy)
    kind "full"     : [b (3), r, s_xx, s_yy, s_xy, s_xz, s_yz] s_zz = −s_xx−s_yy

(the 4-, 7- and 10-element models of NXP AN4246, with W's scale tied to r.) The Jacobian is
analytic: the derivative of expm at a symmetric S comes from the Daleckii–Krein formula in S's
eigenbasis. ``solve`` runs Levenberg–Marquardt (scipy's MINPACK) for the plain loss and a
trust-region solver for robust losses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .failure import FitFailure

KINDS = ("sphere", "diagonal", "full")
N_SHAPE = {"sphere": 0, "diagonal": 2, "full": 5}


def n_params(kind: str) -> int:
    return 4 + N_SHAPE[kind]


def _basis(kind: str) -> list[np.ndarray]:
    """dS/ds_k for each shape parameter."""
    out = []
    if kind in ("diagonal", "full"):
        for i in (0, 1):
            e = np.zeros((3, 3))
            e[i, i] = 1.0
            e[2, 2] = -1.0
            out.append(e)
    if kind == "full":
        for i, j in ((0, 1), (0, 2), (1, 2)):
            e = np.zeros((3, 3))
            e[i, j] = e[j, i] = 1.0
            out.append(e)
    return out


def shape_matrix(kind: str, s) -> np.ndarray:
    S = np.zeros((3, 3))
    for sk, e in zip(np.asarray(s, dtype=np.float64).reshape(-1), _basis(kind)):
        S += sk * e
    return S


def expm_sym(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """expm of a symmetric matrix, with its eigen-decomposition (for the derivative)."""
    lam, Q = np.linalg.eigh(0.5 * (S + S.T))
    return (Q * np.exp(lam)) @ Q.T, lam, Q


def expm_derivatives(kind: str, s) -> tuple[np.ndarray, list[np.ndarray]]:
    """W = expm(S(s)) and dW/ds_k (Daleckii–Krein: dW = Q (F ∘ Qᵀ dS Q) Qᵀ)."""
    W, lam, Q = expm_sym(shape_matrix(kind, s))
    el = np.exp(lam)
    dl = lam[:, None] - lam[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        F = np.where(np.abs(dl) > 1e-12, (el[:, None] - el[None, :]) / np.where(dl == 0, 1, dl), 0.0)
    avg = 0.5 * (el[:, None] + el[None, :])
    F = np.where(np.abs(dl) > 1e-12, F, avg)
    return W, [Q @ (F * (Q.T @ e @ Q)) @ Q.T for e in _basis(kind)]


def unpack(theta, kind: str) -> tuple[np.ndarray, float, np.ndarray]:
    """θ → (offset b (3,), radius r, W (3×3) SPD with det 1)."""
    theta = np.asarray(theta, dtype=np.float64)
    W, _ = expm_derivatives(kind, theta[4:])
    return theta[:3].copy(), float(theta[3]), W


def pack(offset_ut, field_ut, kind: str, W=None) -> np.ndarray:
    """(b, r, W) → θ; W (SPD) is normalised to det 1 and projected onto the kind's shape space."""
    theta = np.zeros(n_params(kind))
    theta[:3] = offset_ut
    theta[3] = field_ut
    if kind != "sphere" and W is not None:
        lam, Q = np.linalg.eigh(0.5 * (np.asarray(W) + np.asarray(W).T))
        L = (Q * np.log(lam)) @ Q.T
        L -= np.trace(L) / 3.0 * np.eye(3)
        if kind == "diagonal":
            theta[4:] = [L[0, 0], L[1, 1]]
        else:
            theta[4:] = [L[0, 0], L[1, 1], L[0, 1], L[0, 2], L[1, 2]]
    return theta


def residual(theta, m: np.ndarray, kind: str) -> np.ndarray:
    b, r, W = unpack(theta, kind)
    return np.linalg.norm((m - b) @ W.T, axis=1) - r


def jacobian(theta, m: np.ndarray, kind: str) -> np.ndarray:
    theta = np.asarray(theta, dtype=np.float64)
    W, dWs = expm_derivatives(kind, theta[4:])
    d = m - theta[:3]
    h = d @ W.T
    nh = np.linalg.norm(h, axis=1)
    u = h / np.where(nh > 0, nh, 1.0)[:, None]
    J = np.empty((len(m), n_params(kind)))
    J[:, :3] = -(u @ W)
    J[:, 3] = -1.0
    for k, dW in enumerate(dWs):
        J[:, 4 + k] = np.einsum("ij,ij->i", u, d @ dW.T)
    return J


@dataclass(frozen=True)
class GeometricFit:
    kind: str
    theta: np.ndarray
    residual_ut: np.ndarray
    jac: np.ndarray
    n_iter: int

    @property
    def offset_ut(self) -> np.ndarray:
        return self.theta[:3]

    @property
    def field_ut(self) -> float:
        return float(self.theta[3])

    @property
    def soft_iron(self) -> np.ndarray:
        return unpack(self.theta, self.kind)[2]

    @property
    def rms_ut(self) -> float:
        return float(np.sqrt(np.mean(self.residual_ut**2)))

    def __bool__(self) -> bool:
        return True


def _weighted(fun, sw):
    return lambda theta, m, kind: sw * fun(theta, m, kind) if fun is residual else sw[:, None] * fun(theta, m, kind)


def solve(
    m_ut: np.ndarray, kind: str, theta0, loss: str = "linear", f_scale_ut: float = 1.0, max_nfev: int = 200,
    weights=None,
) -> GeometricFit | FitFailure:
    """Minimise Σ w_i ρ(e_i) from θ0. ``loss`` is scipy's: linear (ML), huber, soft_l1, cauchy.
    ``weights`` (n,) are inverse noise variances relative to one another (None: all equal)."""
    if kind not in KINDS:
        raise ValueError(f"unknown model kind {kind!r} (one of {', '.join(KINDS)})")
    m = np.asarray(m_ut, dtype=np.float64).reshape(-1, 3)
    p = n_params(kind)
    if len(m) < p + 1:
        return FitFailure("too_few_samples", f"{len(m)} samples; the {kind} model has {p} parameters")
    theta0 = np.asarray(theta0, dtype=np.float64)
    # work about the start's centre and in units of its radius: well-scaled steps
    centre, scale = theta0[:3].copy(), max(abs(theta0[3]), 1e-9)
    mc = (m - centre) / scale
    t0 = theta0.copy()
    t0[:3] = 0.0
    t0[3] = theta0[3] / scale
    method = "lm" if loss == "linear" else "trf"
    if weights is None:
        fun, jac = residual, jacobian
    else:
        sw = np.sqrt(np.asarray(weights, dtype=np.float64).reshape(-1))
        if len(sw) != len(m) or not np.all(np.isfinite(sw)) or np.any(sw < 0):
            raise ValueError("weights must be finite, non-negative, one per sample")
        fun, jac = _weighted(residual, sw), _weighted(jacobian, sw)
    try:
        res = least_squares(
            fun, t0, jac=jac, args=(mc, kind), method=method, loss=loss,
            f_scale=f_scale_ut / scale, x_scale=1.0, max_nfev=max_nfev * (p + 1) if method == "lm" else max_nfev,
            xtol=1e-12, ftol=1e-12, gtol=1e-12,
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        return FitFailure("no_convergence", f"{kind} fit failed: {exc}")
    theta = res.x.copy()
    if not np.all(np.isfinite(theta)) or res.status <= 0:
        return FitFailure("no_convergence", f"{kind} fit did not converge ({res.message})")
    theta[:3] = centre + scale * theta[:3]
    theta[3] = scale * theta[3]
    if theta[3] < 0:  # |h| − r with r < 0 cannot be a minimum unless all |h| ≈ 0
        return FitFailure("degenerate", f"{kind} fit produced a negative radius")
    e = residual(theta, m, kind)
    J = jacobian(theta, m, kind)
    return GeometricFit(kind=kind, theta=theta, residual_ut=e, jac=J, n_iter=int(res.nfev))
