"""Pure degree-3 and degree-4 spherical-harmonic functions of the field direction.

A linear sensor error shows in a sphere fit's residual as degrees 0–2 (docs/physics.md, "The residual of a sphere fit"); degrees
≥ 3 are something else (nonlinearity, field gradients, an imperfect environment). Real
recordings carry such direction-dependent residue, and when the mix of directions changes
during a recording a slow channel (temperature) times the direction can soak it up. Diagnosis
therefore adds these functions as nuisance regressors when it tests soft iron and channels, so
a channel effect must be more than a direction-dependent misfit seen at different times.

The functions are the degree-3 and degree-4 monomials with their lower-degree parts removed
(least squares over a uniform spherical design), so they are orthogonal to degrees 0–2 over
the sphere. Over a band of directions, or any coverage that is not uniform, they are not: a
degree-4 function restricted to a band shares a large part with degree-2 ones, and as a
nuisance it soaks up soft iron. ``on_data`` therefore removes, by least squares over the
recording's own directions, every part of them that degrees 0–2 (the columns of hard iron,
radius and soft iron, as functions of the direction alone) can express. ``TERM`` is that
nuisance as a row of the design's table (magcal.diagnose.design.CATALOGUE).
"""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations_with_replacement

import numpy as np

from .catalogue import CatalogueEffect, Columns, Linearised, Role


def _monomials(u: np.ndarray, degree: int) -> np.ndarray:
    """All monomials of the given degree in u's three components, (n, count)."""
    out = []
    for c in combinations_with_replacement(range(3), degree):
        col = u[:, c[0]].copy()
        for i in c[1:]:
            col *= u[:, i]
        out.append(col)
    return np.stack(out, axis=1)


@lru_cache(maxsize=1)
def _coefficients():
    k = 4000  # Fibonacci sphere: a near-uniform design
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    q = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    out = []
    for deg, lower in ((3, (1,)), (4, (0, 2))):
        p = _monomials(q, deg)
        low = np.concatenate([_monomials(q, d) if d else np.ones((k, 1)) for d in lower], axis=1)
        c, *_ = np.linalg.lstsq(low, p, rcond=None)
        out.append((deg, lower, c))
    return out


def regressors(u: np.ndarray) -> np.ndarray:
    """(n, 25) columns spanning the degree-3 (7-dim) and degree-4 (9-dim) harmonics of unit
    directions u (n, 3); the columns are redundant, rank 16."""
    cols = []
    for deg, lower, c in _coefficients():
        p = _monomials(u, deg)
        low = np.concatenate([_monomials(u, d) if d else np.ones((len(u), 1)) for d in lower], axis=1)
        cols.append(p - low @ c)
    return np.concatenate(cols, axis=1)


def on_data(u: np.ndarray) -> np.ndarray:
    """The harmonics of ``regressors`` made orthogonal, on these directions u (n, 3), to every
    polynomial of degree ≤ 2 in u: they can no longer stand in for offset, radius or soft iron.
    The low-degree functions are of the direction alone (no |m|), so the noise along the field,
    which the residual carries, does not enter them."""
    low = np.concatenate([np.ones((len(u), 1)), u, _monomials(u, 2)], axis=1)
    h = regressors(u)
    coef = np.linalg.lstsq(low, h, rcond=None)[0]
    return h - low @ coef


def columns(lin: Linearised) -> Columns:
    """The harmonics on the directions the design is linearised at (``on_data``), a nuisance of every test."""
    return Columns(on_data(lin.directions))


TERM = CatalogueEffect("direction_harmonics", Role.NUISANCE, columns)
