"""Ellipsoid (soft iron): an ellipsoid-specific algebraic start, the quadric → correction
mapping, then the ML refinement on the geometric residual (``geometric``, W = expm(S) SPD).

Quadric: xᵀAx + Bx + c = 0 (A symmetric 3×3, B a row 3-vector). It is an ellipsoid iff A is
definite. The correction mapping of the ellipsoid note (seed 001): with A = PΛPᵀ,

    X = P S (Pᵀx + ½ Λ⁻¹ (BP)ᵀ),   S = diag(√λ_i) / √w,   w = ¼ B A⁻¹ Bᵀ − c

maps the ellipsoid onto the unit sphere; since Pᵀx + ½Λ⁻¹(BP)ᵀ = Pᵀ(x − x₀) with the centre
x₀ = −½ A⁻¹ Bᵀ, this is X = W₁ (x − x₀) with W₁ = P S Pᵀ symmetric positive definite.

Algebraic start (Li & Griffiths 2004, "Least squares ellipsoid specific fitting"): minimise
‖Dv‖² subject to 4J − I² = 1 with I = a+b+c, J = ab+bc+ca — a generalised eigenproblem whose
single positive eigenvalue gives an ellipsoid for any data whose short/long axis ratio
exceeds ½ (always true for a magnetometer). With thin coverage the plain algebraic quadric
(``algebraic_quadric(..., ellipsoid_specific=False)``) can come out a hyperboloid;
``quadric_to_correction`` detects that (A not definite) and returns a FitFailure, and
``fit_ellipsoid`` then starts from the sphere instead.
"""

from __future__ import annotations

import numpy as np

from . import geometric
from .failure import FitFailure


def _design(m: np.ndarray) -> np.ndarray:
    x, y, z = m.T
    return np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones(len(m))])


def _unpack_v(v: np.ndarray):
    a, b, c, f, g, h, p, q, r, d = v
    A = np.array([[a, h, g], [h, b, f], [g, f, c]])
    B = 2.0 * np.array([p, q, r])
    return A, B, float(d)


def algebraic_quadric(m_ut, ellipsoid_specific: bool = True):
    """Quadric (A, B, c) through (n, 3) points, fitted about their mean and scaled to unit RMS
    (then mapped back). Li–Griffiths constrained when ``ellipsoid_specific``; otherwise the
    plain algebraic quadric with ‖v‖ = 1 (smallest singular vector). FitFailure on < 10 points."""
    m = np.asarray(m_ut, dtype=np.float64).reshape(-1, 3)
    if len(m) < 10:
        return FitFailure("too_few_samples", f"{len(m)} samples; a quadric needs at least 10")
    mu = m.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((m - mu) ** 2, axis=1))))
    if not np.isfinite(s) or s <= 0:
        return FitFailure("degenerate", "all samples are at one point")
    D = _design((m - mu) / s)
    if ellipsoid_specific:
        S = D.T @ D
        S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
        try:
            T = -np.linalg.solve(S22, S12.T)
        except np.linalg.LinAlgError:
            return FitFailure("ill_conditioned", "the samples cannot determine a quadric")
        M = S11 + S12 @ T
        k = 4.0
        C = np.zeros((6, 6))
        C[:3, :3] = k / 2.0 - 1.0
        np.fill_diagonal(C[:3, :3], -1.0)
        C[3:, 3:] = -k * np.eye(3)  # J = ab+bc+ca − f² − g² − h² with A's off-diagonals f, g, h
        w, V = np.linalg.eig(np.linalg.solve(C, M))
        V = np.real(V)
        # the constrained minimum: an eigenvector with vᵀCv > 0 (the "positive eigenvalue",
        # ~0 for noiseless data) and the smallest vᵀMv / vᵀCv among those
        vcv = np.einsum("ij,ik,kj->j", V, C, V)
        vmv = np.einsum("ij,ik,kj->j", V, M, V)
        ok = np.flatnonzero(vcv > 1e-12 * np.max(np.abs(vcv)))
        if len(ok) == 0:
            return FitFailure("degenerate", "no ellipsoid-specific solution (constraint not satisfiable)")
        v1 = V[:, ok[np.argmin(vmv[ok] / vcv[ok])]]
        v = np.concatenate([v1, T @ v1])
    else:
        _, _, Vt = np.linalg.svd(D, full_matrices=False)
        v = Vt[-1]
    A, B, c = _unpack_v(v)
    # back to the original coordinates: x' = (x − mu)/s
    A0 = A / s**2
    B0 = B / s - 2.0 * (mu @ A) / s**2
    c0 = c - (B @ mu) / s + float(mu @ A @ mu) / s**2
    return A0, B0, float(c0)


def quadric_to_correction(A, B, c):
    """The note's mapping. Returns (centre x₀ (3,), W₁ (3×3) SPD onto the unit sphere) or a
    FitFailure("not_positive_definite") when the quadric is not an ellipsoid."""
    A = 0.5 * (np.asarray(A, dtype=np.float64) + np.asarray(A, dtype=np.float64).T)
    B = np.asarray(B, dtype=np.float64).reshape(3)
    lam, P = np.linalg.eigh(A)
    if lam[0] < 0 < lam[-1] or np.any(lam == 0):
        return FitFailure(
            "not_positive_definite",
            f"the quadric is not an ellipsoid (eigenvalues {np.round(lam / np.max(np.abs(lam)), 4).tolist()}:"
            " a hyperboloid — the coverage cannot determine the shape)",
        )
    if lam[-1] < 0:  # negative definite: flip the whole equation
        A, B, c, lam = -A, -B, -c, -lam[::-1]
        lam, P = np.linalg.eigh(A)
    BP = B @ P
    w = float(0.25 * np.sum(BP**2 / lam) - c)
    if w <= 0:
        return FitFailure("degenerate", "the quadric is an empty (imaginary) ellipsoid")
    Sd = np.sqrt(lam) / np.sqrt(w)
    centre = -0.5 * P @ (BP / lam)
    W1 = (P * Sd) @ P.T
    return centre, 0.5 * (W1 + W1.T)


def correct_with_note(x, A, B, c) -> np.ndarray:
    """The note's formula applied literally, X = P S (Pᵀx + ½Λ⁻¹(BP)ᵀ), for (n, 3) points."""
    A = 0.5 * (np.asarray(A, dtype=np.float64) + np.asarray(A, dtype=np.float64).T)
    lam, P = np.linalg.eigh(A)
    if lam[-1] < 0:
        A, B, c = -A, -np.asarray(B), -c
        lam, P = np.linalg.eigh(A)
    BP = np.asarray(B, dtype=np.float64) @ P
    w = float(0.25 * np.sum(BP**2 / lam) - c)
    S = np.diag(np.sqrt(lam) / np.sqrt(w))
    inner = np.atleast_2d(x) @ P + 0.5 * BP / lam
    return inner @ S.T @ P.T


def algebraic_start(m_ut, kind: str):
    """θ for ``geometric`` from the ellipsoid-specific quadric, or a FitFailure."""
    q = algebraic_quadric(m_ut, ellipsoid_specific=True)
    if isinstance(q, FitFailure):
        return q
    corr = quadric_to_correction(*q)
    if isinstance(corr, FitFailure):
        return corr
    centre, W1 = corr
    det = float(np.linalg.det(W1))
    W = W1 / det ** (1.0 / 3.0)
    r = det ** (-1.0 / 3.0)  # |W (m − x₀)| = |W₁ (m − x₀)| / det^(1/3) = det^(−1/3)
    return geometric.pack(centre, r, kind, W)


def fit_ellipsoid(m_ut, kind: str = "full", start=None, loss: str = "linear", f_scale_ut: float = 1.0):
    """ML ellipsoid (``kind`` "diagonal" or "full"). ``start`` a θ (e.g. from the ML sphere);
    without one the ellipsoid-specific algebraic start is used, falling back to the sphere's
    accumulator start when that start is not an ellipsoid."""
    if kind not in ("diagonal", "full"):
        raise ValueError(f"ellipsoid kind must be 'diagonal' or 'full', not {kind!r}")
    m = np.asarray(m_ut, dtype=np.float64).reshape(-1, 3)
    if start is None:
        start = algebraic_start(m, kind)
        if isinstance(start, FitFailure):
            from .sphere import sphere_start

            s0 = sphere_start(m)
            if isinstance(s0, FitFailure):
                return s0
            start = np.concatenate([s0, np.zeros(geometric.N_SHAPE[kind])])
    else:
        start = np.asarray(start, dtype=np.float64)
        if len(start) == 4:
            start = np.concatenate([start, np.zeros(geometric.N_SHAPE[kind])])
        elif len(start) != geometric.n_params(kind):
            b, r, W = geometric.unpack(start, "full" if len(start) == 9 else "diagonal")
            start = geometric.pack(b, r, kind, W)
    return geometric.solve(m, kind, start, loss=loss, f_scale_ut=f_scale_ut)
