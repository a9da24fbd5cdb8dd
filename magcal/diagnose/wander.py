"""The slow offset wander of a real recording, as a nuisance term.

Real recordings wander: the offset moves by a few tenths of a µT over a minute (environment,
1/f noise), and that wander is larger than many of the channel effects diagnosis looks for.
Rather than refusing every channel term that such wander could imitate, the wander is modelled:
an offset that is a smooth function of time, b(t) = Σ_j P_j(τ) δ_j with Legendre polynomials
P_j of degree 2..``degree`` in τ = time scaled to [−1, 1] (the constant is the hard iron and
the straight line is the reportable ``time_drift`` candidate, so neither is in the nuisance).
To first order its radial residual is Σ_j P_j(τ) uᵀδ_j: 3 columns per degree.

Where the residual shows a wander (magcal.diagnose.ladder.wander_seen), every channel term is
then tested and its coefficient estimated from the part of its variation that a smooth
offset-versus-time curve cannot explain; a channel that only varies slowly (a temperature swing
of about a cycle) shares most of its variation with the nuisance, which is the honest statement
that it cannot be told apart from wander in one recording. Where the residual shows none, the
nuisance is left out of the tests: it would only take such a channel's power. ``TERM`` is that
nuisance as the last row of the design's table (magcal.diagnose.design.CATALOGUE), of degree
``NUISANCE_DEGREE``.
"""

from __future__ import annotations

import numpy as np
from numpy.polynomial import legendre

from .catalogue import CatalogueEffect, Columns, Linearised, Role

DEGREE = 4
# the slow wander as a nuisance of the design: Legendre degrees 2..NUISANCE_DEGREE of the offset
# versus time, in every held-out comparison, and in every test where the residual shows a wander
# (ladder.wander_seen)
NUISANCE_DEGREE = 2


def regressors(t_s: np.ndarray, u: np.ndarray, degree: int = DEGREE) -> np.ndarray:
    """(n, 3·(degree−1)) nuisance columns P_j(τ)·u for j = 2..degree; (n, 0) if degree < 2."""
    t = np.asarray(t_s, np.float64)
    n = len(t)
    if degree < 2 or n == 0:
        return np.zeros((n, 0))
    span = float(t[-1] - t[0]) if n > 1 else 0.0
    tau = (2.0 * (t - t[0]) / span - 1.0) if span > 0 else np.zeros(n)
    vand = legendre.legvander(tau, degree)[:, 2:]  # (n, degree−1)
    return (vand[:, :, None] * u[:, None, :]).reshape(n, -1)


def columns(lin: Linearised) -> Columns:
    """The wander nuisance of degree ``NUISANCE_DEGREE`` along the offset's own radial signature W·u."""
    return Columns(regressors(lin.t_s, lin.offset_directions, NUISANCE_DEGREE))


TERM = CatalogueEffect("slow_wander", Role.WANDER, columns)
