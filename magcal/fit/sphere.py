"""Maximum-likelihood sphere: Levenberg–Marquardt on the geometric residual |m − c| − r,
started from the sphere accumulator's algebraic solution.

The algebraic (normal-equation) fit minimises Σ(|m − c|² − r²)², a geometric residual weighted
by |m − c| + r; on partial coverage that weighting biases the centre (docs/physics.md,
"Algebraic and geometric fits": +2.9 µT in z on a ±30° cap). The geometric residual is the
Gaussian likelihood, so this fit reaches the Cramér–Rao bound (see bench/fit_crlb.py).
"""

from __future__ import annotations

import numpy as np

from . import geometric
from .accumulator import DEFAULT_MAX_CONDITION, SphereAccumulator
from .failure import FitFailure


def sphere_start(m_ut, max_condition: float = DEFAULT_MAX_CONDITION):
    """θ = [c (3), r] from the accumulator, or its FitFailure."""
    acc = SphereAccumulator()
    acc.add_batch(m_ut)
    alg = acc.solve(max_condition=max_condition)
    if isinstance(alg, FitFailure):
        return alg
    return np.concatenate([alg.offset_ut, [alg.field_ut]])


def fit_sphere(m_ut, start=None, loss: str = "linear", f_scale_ut: float = 1.0) -> geometric.GeometricFit | FitFailure:
    m = np.asarray(m_ut, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(m)):
        return FitFailure("non_finite", "samples contain NaN or infinity")
    if start is None:
        start = sphere_start(m)
        if isinstance(start, FitFailure):
            return start
    return geometric.solve(m, "sphere", np.asarray(start, dtype=np.float64)[:4], loss=loss, f_scale_ut=f_scale_ut)
