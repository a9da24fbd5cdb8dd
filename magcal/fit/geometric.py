"""The geometric (maximum-likelihood) residual shared by the sphere and ellipsoid fits.

Model: h_i = W (m_i − b) has length r. The noise is in the raw samples m_i (isotropic, σ µT),
so the residual of sample i is |h_i| − r expressed in the raw space: to first order a raw
error δm moves |h| by (W û)·δm (û = h/|h|, W symmetric), so

    e_i = (|W (m_i − b)| − r) / ‖W û_i‖        (µT of raw error; least squares = ML)

Measured in the calibrated space instead (|h| − r alone) the sum is smallest when the gains the
samples see most are shrunk — |h| − r is scaled by them — and, with det W = 1, the cost goes to
the gains the samples see least: on a ±9° band of tilts that gave a fitted ellipsoid *below*
the true one's residual and a 4 % error along the unseen directions. For a sphere ‖W û‖ = 1 and
both residuals are the same.

W = expm(S) with S symmetric and trace S = 0, so W is symmetric positive definite with det W = 1
for every parameter value — the fit can never produce a non-PD matrix, and the overall scale,
which magnitudes cannot separate from |h|, sits in r alone. Parameter vector θ:

    kind "sphere"   : [b (3), r]                               S = 0
    kind "diagonal" : [b (3), r, s_xx, s_yy]                   S = diag(s_xx, s_yy, −s_xx−s_yy)
    kind "full"     : [b (3), r, s_xx, s_yy, s_xy, s_xz, s_yz] s_zz = −s_xx−s_yy

(the 4-, 7- and 10-element models of NXP AN4246, with W's scale tied to r.) The Jacobian is
analytic: the derivative of expm at a symmetric S comes from the Daleckii–Krein formula in S's
eigenbasis. ``solve`` runs Levenberg–Marquardt with Marquardt's diagonal scaling (numpy only:
at most 10 parameters, so the normal equations are tiny); a robust loss (soft_l1, huber,
cauchy) is minimised by the same steps on iteratively re-weighted residuals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .failure import FitFailure

# the model kinds, simplest first: the one order of models (the tracker grows through them in it;
# a held-out tie goes to the earlier one, fit.holdout)
KINDS = ("sphere", "diagonal", "full")
N_SHAPE = {"sphere": 0, "diagonal": 2, "full": 5}


def n_params(kind: str) -> int:
    return 4 + N_SHAPE[kind]


def _basis_of(kind: str) -> tuple[np.ndarray, ...]:
    """dS/ds_k for each shape parameter (read-only)."""
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
    for e in out:
        e.flags.writeable = False
    return tuple(out)


_BASES = {kind: _basis_of(kind) for kind in KINDS}
# the same, stacked (k, 3, 3): one matrix product for every derivative (a product over a stack
# is made matrix by matrix, the same numbers as a product per matrix)
_STACKED = {kind: np.array(_BASES[kind]).reshape(-1, 3, 3) for kind in KINDS}
for _stack in _STACKED.values():
    _stack.flags.writeable = False


def _basis(kind: str) -> tuple[np.ndarray, ...]:
    """dS/ds_k for each shape parameter: constants, made once (read-only)."""
    return _BASES[kind]


def shape_matrix(kind: str, s) -> np.ndarray:
    """S = Σ_k s_k dS/ds_k. Each entry is written as that sum makes it (0 + the terms that are
    not zero, in order: adding a zero term changes no value), without a pass over the basis."""
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    if kind == "sphere":
        return np.zeros((3, 3))
    if len(s) != N_SHAPE[kind] or not np.isfinite(s).all():  # a zero term times inf or nan is nan
        return _summed_shape_matrix(kind, s)
    a, b = float(s[0]), float(s[1])
    S = np.zeros((3, 3))
    S[0, 0], S[1, 1], S[2, 2] = 0.0 + a, 0.0 + b, (0.0 + -a) + -b
    if kind == "full":
        S[0, 1] = S[1, 0] = 0.0 + float(s[2])
        S[0, 2] = S[2, 0] = 0.0 + float(s[3])
        S[1, 2] = S[2, 1] = 0.0 + float(s[4])
    return S


def _summed_shape_matrix(kind: str, s: np.ndarray) -> np.ndarray:
    S = np.zeros((3, 3))
    for sk, e in zip(s, _basis(kind)):
        S += sk * e
    return S


def expm_sym(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """expm of a symmetric matrix, with its eigen-decomposition (for the derivative)."""
    lam, Q = np.linalg.eigh(0.5 * (S + S.T))
    return (Q * np.exp(lam)) @ Q.T, lam, Q


def expm_derivatives(kind: str, s, eig=None) -> tuple[np.ndarray, np.ndarray]:
    """W = expm(S(s)) and dW/ds_k stacked (k, 3, 3) (Daleckii–Krein: dW = Q (F ∘ Qᵀ dS Q) Qᵀ);
    ``eig``: expm_sym's (W, λ, Q) at the same s when already computed."""
    W, lam, Q = expm_sym(shape_matrix(kind, s)) if eig is None else eig
    return W, Q @ (_divided_differences(lam) * (Q.T @ _STACKED[kind] @ Q)) @ Q.T


def _divided_differences(lam: np.ndarray) -> np.ndarray:
    """F_ij = (e^λi − e^λj)/(λi − λj), or the mean of the two where λi and λj are within 1e-12
    (the limit, e^λ): nine scalars, each the one operation an array would make of it."""
    el, lam = np.exp(lam).tolist(), lam.tolist()
    return np.array([[(ei - ej) / (li - lj) if abs(li - lj) > 1e-12 else 0.5 * (ei + ej) for ej, lj in zip(el, lam)]
                     for ei, li in zip(el, lam)])


def unpack(theta, kind: str) -> tuple[np.ndarray, float, np.ndarray]:
    """θ → (offset b (3,), radius r, W (3×3) SPD with det 1)."""
    theta = np.asarray(theta, dtype=np.float64)
    W = expm_sym(shape_matrix(kind, theta[4:]))[0]  # expm_derivatives's W, without the derivatives
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


def _forward(theta: np.ndarray, mt: np.ndarray, kind: str) -> tuple:
    """(d = m − b, h = W d, |h|, expm_sym's (W, λ, Q), ‖W û‖) at θ for samples given as columns,
    ``mt`` (3, n): what the residual and the Jacobian share. d and h are (3, n) too — an axis at
    a time over all samples, contiguous (a subtraction over rows of three costs seven times as
    much; the products are the same numbers). For the sphere W = expm(0) = I exactly, so h is d
    itself (the product by I is exact), the eigen-decomposition is not made and the raw-space
    scale ‖W û‖ is one: both None."""
    d = mt - theta[:3, None]
    if kind == "sphere":
        return d, d, _column_norm(d), None, None
    eig = expm_sym(shape_matrix(kind, theta[4:]))
    h = eig[0] @ d
    nh = _column_norm(h)
    scale = _column_norm(eig[0] @ h)
    scale /= np.where(nh > 0, nh, 1.0)
    return d, h, nh, eig, scale


def _residual_of(forward: tuple, r: float) -> np.ndarray:
    """e = (|h| − r) / ‖W û‖ from ``_forward``'s values."""
    nh, scale = forward[2], forward[4]
    return nh - r if scale is None else (nh - r) / scale


def _columns(m: np.ndarray) -> np.ndarray:
    """(3, n) contiguous: the samples' axes as rows."""
    return np.ascontiguousarray(np.asarray(m, dtype=np.float64).T)


def row_norm(v: np.ndarray) -> np.ndarray:
    """|v_i| of the rows of an (n, 3) array: the sums np.linalg.norm(v, axis=1) makes, in its
    order, column by column (its reduction over a short last axis costs five times as much)."""
    x, y, z = (v * v).T
    return np.sqrt((x + y) + z)


def _column_norm(vt: np.ndarray) -> np.ndarray:
    """row_norm of vt.T for vt (3, n): the same sums, in the same order."""
    x, y, z = vt
    out, square = x * x, y * y
    out += square
    out += np.multiply(z, z, out=square)
    return np.sqrt(out, out=out)


def residual(theta, m: np.ndarray, kind: str) -> np.ndarray:
    """e_i (µT of raw error) of the samples ``m`` (n, 3) at θ."""
    theta = np.asarray(theta, dtype=np.float64)
    return _residual_of(_forward(theta, _columns(m), kind), float(theta[3]))


def residual_jacobian(theta, m: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(``residual``, ``jacobian``) at θ from one evaluation."""
    theta = np.asarray(theta, dtype=np.float64)
    fwd = _forward(theta, _columns(m), kind)
    return _residual_of(fwd, float(theta[3])), jacobian(theta, m, kind, fwd)


def jacobian(theta, m: np.ndarray, kind: str, forward=None) -> np.ndarray:
    """∂e/∂θ (n, p); ``forward``: ``_forward`` at the same θ when already computed. Built a
    parameter at a time over all samples (rows of its transpose, each contiguous).

    With g = |h| − r, u = h/|h|, v = W u and s = |v| (e = g/s): ∂g/∂b = −v, ∂g/∂r = −1,
    ∂g/∂s_k = Σ_ij u_i d_j (∂W/∂s_k)_ij; and with p = (I − u uᵀ) W v/s (the part of W v/s across
    u), ∂s/∂b = −W p/|h|, ∂s/∂r = 0, ∂s/∂s_k = Σ_ij (v_i u_j/s + p_i d_j/|h|) (∂W/∂s_k)_ij.
    Then ∂e = ∂g/s − g ∂s/s². The second term is what moves the estimate off the
    calibrated-space one: it is small per sample (g ~ σ) but not in the sum."""
    theta = np.asarray(theta, dtype=np.float64)
    d, h, nh, eig, scale = forward if forward is not None else _forward(theta, _columns(m), kind)
    nz = np.where(nh > 0, nh, 1.0)
    ut = h / nz
    jt = np.empty((n_params(kind), d.shape[1]))
    if kind == "sphere":  # W = I, s = 1: −Wu is −u exactly
        np.negative(ut, out=jt[:3])
        jt[3] = -1.0
        return jt.T
    W, dWs = expm_derivatives(kind, theta[4:], eig)
    # the products below are made in place where a temporary would hold the same numbers
    inv_nh = np.divide(1.0, nz, out=nz)
    inv_s = 1.0 / scale
    vs = W @ ut
    vs *= inv_s
    a = W @ vs
    dot = ut[0] * a[0]
    dot += ut[1] * a[1]
    dot += ut[2] * a[2]
    qt = np.multiply(ut, dot, out=np.empty_like(ut))
    np.subtract(a, qt, out=qt)
    qt *= inv_nh  # p/|h|
    c = nh - float(theta[3])
    c *= inv_s * inv_s  # g/s²
    wq = W @ qt
    wq *= c
    np.subtract(wq, vs, out=jt[:3])
    np.negative(inv_s, out=jt[3])
    # Σ_ij (∂W/∂s_k)_ij X_ij with X = u dᵀ/s − g/s² (v uᵀ/s + p dᵀ/|h|) = α dᵀ + β uᵀ,
    # α = u/s − g/s² · p/|h| and β = −g/s² · v/s: the nine products α_i d_j + β_i u_j as rows
    # (same-shape products: a broadcast over a (3, 3, n) array, in a tenth of the calls, is no
    # faster at 4000 samples, numpy copying its operands through its buffers)
    alpha = ut * inv_s
    alpha -= np.multiply(qt, c, out=wq)
    beta = np.multiply(vs, np.negative(c, out=c), out=vs)
    x, product = np.empty((9, d.shape[1])), dot
    for i in range(3):
        for j in range(3):
            np.multiply(alpha[i], d[j], out=x[3 * i + j])
            x[3 * i + j] += np.multiply(beta[i], ut[j], out=product)
    np.matmul(dWs.reshape(len(dWs), 9), x, out=jt[4:])
    return jt.T


@dataclass(frozen=True)
class GeometricFit:
    """A solved model: θ, its residual and, on first use, its Jacobian (``jac``), built from
    ``at`` — θ as solved, the samples (a private copy) and ``_forward``'s values there, which
    the residual came from. A fit whose Jacobian nobody reads (a robust start, a Grubbs round
    before the last, a first reweighting pass) never builds it; where it is read it is the
    same numbers."""

    kind: str
    theta: np.ndarray
    residual_ut: np.ndarray
    n_iter: int
    at: tuple = field(default=(), repr=False, compare=False)  # (θ, the samples as columns (3, n), _forward's values)

    @cached_property
    def jac(self) -> np.ndarray:
        theta, mt, fwd = self.at
        return jacobian(theta, mt.T, self.kind, fwd)

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




LOSSES = ("linear", "soft_l1", "huber", "cauchy")


def _rho(loss: str, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ρ(z) and ρ'(z) of a loss at z = (e / f)² (scipy's definitions: ρ ≈ z near 0)."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "soft_l1":
        q = np.sqrt(1.0 + z)
        return 2.0 * (q - 1.0), 1.0 / q
    if loss == "huber":
        big = z > 1.0
        sq = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2.0 * sq - 1.0, z), np.where(big, 1.0 / sq, 1.0)
    return np.log1p(z), 1.0 / (1.0 + z)  # cauchy


def _cost(e: np.ndarray, loss: str, f: float) -> tuple[float, np.ndarray | None]:
    """(½ f² Σ ρ((e/f)²), the IRLS weights ρ' there — None for the plain loss, whose are ones):
    the weights of the point whose cost was made, kept for its normal equations."""
    z = (e / f) ** 2
    if loss == "linear":
        return 0.5 * f * f * float(z.sum()), None
    rho, weights = _rho(loss, z)
    return 0.5 * f * f * float(rho.sum()), weights


@dataclass(frozen=True)
class DampedStep:
    """A damped step that lowered the cost: the new point, its cost, the damping that gave it,
    and whatever the evaluation returned beside the cost (a residual, a state to reuse)."""

    x: np.ndarray
    cost: float
    lam: float
    aux: object


def damped_step(evaluate, x, A, g, cost: float, lam: float, max_tries: int = 64,
                lam_max: float = 1e16) -> DampedStep | None:
    """The one damped normal-equation step every iterative fit in magcal takes: solve
    (A + λ·diag A) δ = −g (Marquardt's scaling, solved Jacobi-equilibrated so a badly scaled A
    keeps its digits) and accept x + δ when ``evaluate`` (x → (cost, aux)) gives a finite cost
    no larger than ``cost``; otherwise λ ×10 and again. None: no step within ``max_tries`` or
    below ``lam_max`` lowers the cost (the point is a minimum to working precision)."""
    ds = np.sqrt(np.maximum(np.diag(A), 1e-300))
    a, gs = A / np.outer(ds, ds), g / ds
    eye = np.eye(len(ds))
    for _ in range(max_tries):
        try:
            x_new = x - np.linalg.solve(a + lam * eye, gs) / ds
        except np.linalg.LinAlgError:
            x_new = None
        if x_new is not None and np.isfinite(x_new).all():
            cost_new, aux = evaluate(x_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                return DampedStep(x_new, float(cost_new), lam, aux)
        lam *= 10.0
        if lam > lam_max:
            return None
    return None


def levenberg_marquardt(fun, jac, x0, loss: str = "linear", f_scale: float = 1.0, max_iter: int = 200,
                        tol: float = 1e-12) -> tuple[np.ndarray, int, bool]:
    """Minimise ½ f² Σ ρ((fun(x)/f)²) from x0: (x, function evaluations, converged).

    Each step (``damped_step``) solves (JᵀWJ + λ·diag(JᵀWJ)) δ = −JᵀWe with W = ρ'(z) (all ones
    for the plain loss: Levenberg–Marquardt; otherwise iteratively re-weighted least squares,
    whose fixed points are the loss's stationary points). λ shrinks after a step that lowers
    the cost and grows after one that does not. Converged when a step changes x by less than
    ``tol`` relative, or the cost by less than ``tol`` relative."""
    x = np.asarray(x0, dtype=np.float64).copy()
    e = fun(x)
    (cost, w), nfev, lam = _cost(e, loss, f_scale), [1], 1e-3

    def evaluate(x_new):
        nfev[0] += 1
        e_new = fun(x_new)
        cost_new, w_new = _cost(e_new, loss, f_scale) if np.isfinite(e_new).all() else (np.inf, None)
        return cost_new, (e_new, w_new)

    for _ in range(max_iter):
        A, g = _normal_equations(jac(x), e, w)
        step = damped_step(evaluate, x, A, g, cost, lam)
        if step is None:
            return x, nfev[0], True  # no step lowers the cost: at the minimum to machine precision
        small_step = _norm(step.x - x) <= tol * (_norm(x) + tol)
        small_gain = cost - step.cost <= tol * cost
        x, (e, w), cost, lam = step.x, step.aux, step.cost, max(step.lam / 10.0, 1e-12)
        if small_step or small_gain:
            return x, nfev[0], True
    return x, nfev[0], False


def _norm(v: np.ndarray) -> float:
    """np.linalg.norm of a vector: the square root of its dot product with itself (as it makes it)."""
    return math.sqrt(v.dot(v))


def _normal_equations(J, e, w):
    """(JᵀWJ, JᵀWe) with the loss's IRLS weights ``w`` at e (``_cost``'s; None for the plain
    loss, whose weights would multiply by one)."""
    if w is None:
        return J.T @ J, J.T @ e
    return J.T @ (w[:, None] * J), J.T @ (w * e)


def solve(
    m_ut: np.ndarray, kind: str, theta0, loss: str = "linear", f_scale_ut: float = 1.0, max_nfev: int = 200,
    weights=None,
) -> GeometricFit | FitFailure:
    """Minimise Σ w_i ρ(e_i) from θ0. ``loss``: linear (ML), soft_l1, huber, cauchy (scipy's
    definitions). ``weights`` (n,) are inverse noise variances relative to one another (None:
    all equal)."""
    if kind not in KINDS:
        raise ValueError(f"unknown model kind {kind!r} (one of {', '.join(KINDS)})")
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r} (one of {', '.join(LOSSES)})")
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
    sw = np.ones(len(m))
    if weights is not None:
        sw = np.sqrt(np.asarray(weights, dtype=np.float64).reshape(-1))
        if len(sw) != len(m) or not np.all(np.isfinite(sw)) or np.any(sw < 0):
            raise ValueError("weights must be finite, non-negative, one per sample")
    fun, jac = _weighted(_columns(mc), kind, None if weights is None else sw)
    with np.errstate(over="ignore", invalid="ignore"):
        theta, nfev, converged = levenberg_marquardt(fun, jac, t0, loss=loss, f_scale=f_scale_ut / scale,
                                                     max_iter=max_nfev)
    if not np.all(np.isfinite(theta)) or not converged:
        return FitFailure("no_convergence", f"{kind} fit did not converge in {max_nfev} steps")
    theta[:3] = centre + scale * theta[:3]
    theta[3] = scale * theta[3]
    if theta[3] < 0:  # |h| − r with r < 0 cannot be a minimum unless all |h| ≈ 0
        return FitFailure("degenerate", f"{kind} fit produced a negative radius")
    mt = _columns(m)
    fwd = _forward(theta, mt, kind)
    return GeometricFit(kind=kind, theta=theta, residual_ut=_residual_of(fwd, float(theta[3])), n_iter=nfev,
                        at=(theta.copy(), mt, fwd))


def _weighted(mt: np.ndarray, kind: str, sw: np.ndarray | None):
    """The residual and Jacobian functions Levenberg–Marquardt steps with (rows times ``sw``,
    the square-root weights; None: unweighted), for samples as columns ``mt`` (3, n). It asks
    for the Jacobian at the point whose residual it evaluated last, so the two share that
    evaluation (m − b, W(m − b), its norm)."""
    last: list = [None, None]

    def fun(t):
        fwd = _forward(t, mt, kind)
        last[:] = [t, fwd]  # Levenberg–Marquardt never writes into a point it evaluated
        e = _residual_of(fwd, float(t[3]))
        return e if sw is None else sw * e

    def jac(t):
        fwd = last[1] if last[0] is t else None
        J = jacobian(t, mt.T, kind, fwd)
        return J if sw is None else sw[:, None] * J

    return fun, jac
