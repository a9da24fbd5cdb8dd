"""The extended calibration model diagnosis fits, and its Gauss–Newton fit.

Model (sensor frame, µT), per sample i with auxiliary channels x_c::

    h_i = W (m_i − b − Σ_c K_c (x_ci − ref_c))        e_i = |h_i| − r

W is symmetric with trace 3 (the overall scale trades with r, docs/physics.md, "Identifiability"),
parametrised as I + Σ_p s_p E_p over an orthonormal basis of trace-free symmetric matrices —
the five degree-2 directions of the sphere-fit residual. b is the offset at the reference
conditions, K_c the µT of offset per unit of channel c.

The fit minimises Σ e_i² (the geometric radial residual) by damped Gauss–Newton from an
algebraic sphere start. It returns a :class:`ModelFit` or a :class:`FitFailure`, never a
half-built object.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..core.calibration import Calibration
from ..fit.accumulator import SphereAccumulator
from ..fit import geometric
from ..fit.failure import FitFailure

_R2 = np.sqrt(2.0)
_R6 = np.sqrt(6.0)
SOFT_BASIS = np.array(
    [
        [[1, 0, 0], [0, -1, 0], [0, 0, 0]],
        [[1, 0, 0], [0, 1, 0], [0, 0, -2]],
        [[0, 1, 0], [1, 0, 0], [0, 0, 0]],
        [[0, 0, 1], [0, 0, 0], [1, 0, 0]],
        [[0, 0, 0], [0, 0, 1], [0, 1, 0]],
    ],
    dtype=np.float64,
) / np.array([_R2, _R6, _R2, _R2, _R2])[:, None, None]


@dataclass(frozen=True)
class Spec:
    """Which terms a model has: soft iron or not, and which channels.

    ``soft_dirs`` (5 × k, as nested tuples) restricts soft iron to the k identifiable
    combinations of SOFT_BASIS (a coverage gate); None means all five."""

    soft_iron: bool = False
    channels: tuple[str, ...] = ()
    soft_dirs: tuple | None = None

    @property
    def soft_matrix(self) -> np.ndarray:
        """(5, k): columns are the fitted soft-iron directions in SOFT_BASIS coordinates."""
        if not self.soft_iron:
            return np.zeros((5, 0))
        return np.eye(5) if self.soft_dirs is None else np.asarray(self.soft_dirs, np.float64).reshape(5, -1)

    @property
    def n_soft(self) -> int:
        return self.soft_matrix.shape[1]

    @property
    def basis(self) -> np.ndarray:
        return np.tensordot(self.soft_matrix.T, SOFT_BASIS, axes=1)  # (k, 3, 3)

    @property
    def n_params(self) -> int:
        return 4 + self.n_soft + 3 * len(self.channels)


@dataclass(frozen=True)
class ModelFit:
    spec: Spec
    params: np.ndarray
    reference: Mapping[str, float]
    rms_ut: float
    n: int
    iterations: int
    cov: np.ndarray | None = field(default=None, repr=False)

    def __bool__(self) -> bool:
        return True

    # -- named parts of the parameter vector --------------------------------------------
    @property
    def offset_ut(self) -> np.ndarray:
        return self.params[0:3]

    @property
    def soft(self) -> np.ndarray:
        """Soft-iron coordinates over all five SOFT_BASIS directions."""
        return self.spec.soft_matrix @ self.params[3 : 3 + self.spec.n_soft]

    @property
    def soft_iron(self) -> np.ndarray:
        return np.eye(3) + np.tensordot(self.soft, SOFT_BASIS, axes=1)

    @property
    def field_ut(self) -> float:
        return float(self.params[3 + self.spec.n_soft])

    @property
    def coef_ut_per_unit(self) -> dict[str, np.ndarray]:
        k0 = 4 + self.spec.n_soft
        return {c: self.params[k0 + 3 * j : k0 + 3 * j + 3].copy() for j, c in enumerate(self.spec.channels)}

    def calibration(self) -> Calibration:
        return Calibration(
            offset_ut=self.offset_ut,
            field_ut=self.field_ut,
            soft_iron=self.soft_iron,
            coef_ut_per_unit=self.coef_ut_per_unit,
            reference={c: self.reference[c] for c in self.spec.channels},
        )

    def residual(self, m: np.ndarray, channels: Mapping[str, np.ndarray]) -> np.ndarray:
        e, _ = residual_jacobian(self.params, self.spec, m, _centred(channels, self.spec, self.reference), False)
        return e

    def jacobian(self, m, channels) -> tuple[np.ndarray, np.ndarray]:
        return residual_jacobian(self.params, self.spec, m, _centred(channels, self.spec, self.reference), True)


def _centred(channels, spec: Spec, reference) -> list[np.ndarray]:
    return [np.asarray(channels[c], np.float64) - float(reference.get(c, 0.0)) for c in spec.channels]


def residual_jacobian(p, spec: Spec, m, xs, want_j=True):
    """Radial residual e (n,) and its Jacobian J (n, n_params) at parameters p."""
    e, state = _forward(p, spec, m, xs)
    return e, (_jacobian(m, xs, state) if want_j else None)


def _forward(p, spec: Spec, m, xs):
    """(e, what the Jacobian at p needs of the residual's evaluation: the soft-iron basis, W,
    d = m − b − the channel terms, h = W d, |h|)."""
    b = p[0:3]
    ns = spec.n_soft
    basis = spec.basis if ns else None
    k0 = 3 + ns
    w = np.eye(3) + np.tensordot(p[3:k0], basis, axes=1) if ns else None
    r = p[k0]
    d = m - b
    for j, x in enumerate(xs):
        d = d - np.outer(x, p[k0 + 1 + 3 * j : k0 + 4 + 3 * j])
    h = d if w is None else d @ w  # w symmetric
    rho = np.sqrt(np.einsum("ij,ij->i", h, h))
    return rho - r, (basis, w, d, h, rho)


def _jacobian(m, xs, state):
    """J (n, n_params), each block of columns written in place."""
    basis, w, d, h, rho = state
    u = h / np.maximum(rho, 1e-12)[:, None]
    wu = u if w is None else u @ w
    ns = 0 if basis is None else len(basis)
    j = np.empty((len(m), 4 + ns + 3 * len(xs)))
    np.negative(wu, out=j[:, 0:3])
    if ns:
        # ∂|h|/∂s_p = uᵀ E_p d, all p at once: (u · [E_1 … E_k]) reshaped, times d
        ue = (u @ basis.transpose(1, 0, 2).reshape(3, 3 * ns)).reshape(len(m), ns, 3)
        j[:, 3 : 3 + ns] = np.einsum("npj,nj->np", ue, d)
    j[:, 3 + ns] = -1.0
    for k, x in enumerate(xs):
        np.multiply(-x[:, None], wu, out=j[:, 4 + ns + 3 * k : 7 + ns + 3 * k])
    return j


def fit_model(
    m: np.ndarray,
    channels: Mapping[str, np.ndarray],
    spec: Spec,
    reference: Mapping[str, float] | None = None,
    start: ModelFit | None = None,
    max_iter: int = 30,
) -> ModelFit | FitFailure:
    """Least-squares fit of the extended model to the radial residual."""
    m = np.asarray(m, np.float64)
    ref = {c: float((reference or {}).get(c, 0.0)) for c in spec.channels}
    if len(m) < spec.n_params + 3:
        return FitFailure("too_few_samples", f"{len(m)} samples cannot determine {spec.n_params} parameters")
    xs = _centred(channels, spec, ref)
    p = np.zeros(spec.n_params)
    if start is not None:
        p[0:3] = start.offset_ut
        ns = spec.n_soft
        k0 = 3 + ns
        if ns:
            p[3:k0] = np.linalg.lstsq(spec.soft_matrix, start.soft, rcond=None)[0]
        p[k0] = start.field_ut
        old = start.coef_ut_per_unit
        for j, c in enumerate(spec.channels):
            if c in old:
                p[k0 + 1 + 3 * j : k0 + 4 + 3 * j] = old[c]
    else:
        acc = SphereAccumulator()
        acc.add_batch(m)
        sph = acc.solve(min_samples=4, max_condition=np.inf)  # a start only: coverage is judged elsewhere
        if not sph:
            return sph
        p[0:3], p[3 + spec.n_soft] = sph.offset_ut, sph.field_ut
    p, cost, j, it = _descend(p, spec, m, xs, max_iter)
    if not np.all(np.isfinite(p)):
        return FitFailure("no_convergence", "the fit diverged")
    if spec.n_soft:
        w = np.eye(3) + np.tensordot(p[3 : 3 + spec.n_soft], spec.basis, axes=1)
        if np.any(np.linalg.eigvalsh(w) <= 0):
            return FitFailure("not_positive_definite", "the fitted soft-iron matrix is not positive definite")
    n = len(m)
    dof = max(n - len(p), 1)
    s2 = cost / dof
    try:
        cov = s2 * np.linalg.pinv(j.T @ j)
    except np.linalg.LinAlgError:
        cov = None
    return ModelFit(spec, p, ref, float(np.sqrt(cost / n)), n, it, cov)


def _descend(p, spec: Spec, m, xs, max_iter: int):
    """Damped Gauss–Newton (``geometric.damped_step``) from p: (p, cost, Jacobian at p, steps)."""
    e, j = residual_jacobian(p, spec, m, xs)
    cost, lam, it = float(e @ e), 1e-6, 0

    def evaluate(p_new):
        e_new, state = _forward(p_new, spec, m, xs)
        return float(e_new @ e_new), (e_new, state)

    for it in range(1, max_iter + 1):
        step = geometric.damped_step(evaluate, p, j.T @ j, j.T @ e, cost, lam, max_tries=12)
        if step is None:
            break
        rel = (cost - step.cost) / max(cost, 1e-300)
        p, cost, lam = step.x, step.cost, max(step.lam / 10, 1e-9)
        e, j = step.aux[0], _jacobian(m, xs, step.aux[1])  # the Jacobian where the residual was just evaluated
        if rel < 1e-10:
            break
    return p, cost, j, it


def fit_with_channel_terms(
    m: np.ndarray,
    channels: Mapping[str, np.ndarray],
    spec: Spec,
    reference: Mapping[str, float],
    coefs: Mapping[str, np.ndarray],
    start: ModelFit | None = None,
) -> ModelFit | FitFailure:
    """The model of ``spec`` with its channel coefficients held at ``coefs`` (estimated
    elsewhere, e.g. by a test that carried nuisance terms) and offset, soft iron and radius
    fitted to the samples with those channel offsets taken out."""
    ref = {c: float(reference.get(c, 0.0)) for c in spec.channels}
    shift = sum((np.outer(np.asarray(channels[c], np.float64) - ref[c], coefs[c]) for c in spec.channels), np.zeros((len(m), 3)))
    inner = Spec(soft_iron=spec.soft_iron, soft_dirs=spec.soft_dirs)
    fit = fit_model(np.asarray(m, np.float64) - shift, {}, inner, start=start)
    if isinstance(fit, FitFailure):
        return fit
    params = np.concatenate([fit.params] + [np.asarray(coefs[c], np.float64) for c in spec.channels])
    return ModelFit(spec, params, ref, fit.rms_ut, fit.n, fit.iterations, None)


# magcal.fit's model names → the soft-iron directions of SOFT_BASIS they carry (None: all five)
_FIT_SOFT_DIRS = {"sphere": (), "ellipsoid_diagonal": ((1.0, 0.0), (0.0, 1.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0)), "ellipsoid": None}


def from_calibration(cal: Calibration, model: str, n: int, rms_ut: float, uncertainty: Mapping | None = None,
                     channel_cov: Mapping | None = None) -> ModelFit:
    """A magcal.fit result (``model`` its name, W with det 1) as a ModelFit of the same shape:
    W rescaled to trace 3 and the radius with it, so |W(m − b)| − r only changes scale. With
    the fit's ``uncertainty`` (1σ of offset_ut and field_ut) the ModelFit carries a diagonal
    covariance of those (soft-iron entries unknown: NaN), and ``channel_cov`` (channel → 3×3)
    adds the blocks of channel terms appended later."""
    dirs = _FIT_SOFT_DIRS[model]
    spec = Spec() if dirs == () else Spec(soft_iron=True, soft_dirs=dirs)
    w = np.asarray(cal.soft_iron, np.float64)
    scale = 3.0 / float(np.trace(w))
    soft = np.einsum("pij,ij->p", SOFT_BASIS, w * scale - np.eye(3))
    coords = np.linalg.lstsq(spec.soft_matrix, soft, rcond=None)[0] if spec.n_soft else np.zeros(0)
    params = np.concatenate([cal.offset_ut, coords, [cal.field_ut * scale]])
    return ModelFit(spec, params, {}, rms_ut * scale, n, 0, _covariance(spec, scale, uncertainty, channel_cov))


def _covariance(spec: Spec, scale: float, uncertainty: Mapping | None, channel_cov: Mapping | None) -> np.ndarray | None:
    if uncertainty is None:
        return None
    chans = list((channel_cov or {}).items())
    k = 4 + spec.n_soft
    cov = np.full((k + 3 * len(chans),) * 2, 0.0)
    cov[np.diag_indices(k)] = np.nan
    cov[np.arange(3), np.arange(3)] = np.asarray(uncertainty["offset_ut"], np.float64) ** 2
    cov[k - 1, k - 1] = (float(uncertainty["field_ut"]) * scale) ** 2
    for j, (_, c) in enumerate(chans):
        if c is not None:
            cov[k + 3 * j : k + 3 * j + 3, k + 3 * j : k + 3 * j + 3] = c
    return cov
