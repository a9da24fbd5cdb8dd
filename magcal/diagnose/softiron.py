"""Soft iron / scale mismatch / non-orthogonality: the degree-2 part of the sphere residual.

The candidate regressors are ∂|h|/∂s_p = uᵀE_p d for the five trace-free symmetric directions
E_p (magcal.diagnose.model.SOFT_BASIS). From magnitudes alone the three causes cannot be told
apart (docs/physics.md, "Identifiability"), so they are one effect with one symmetric matrix.
``TERM`` is the effect as a row of the design's table (magcal.diagnose.design.CATALOGUE).
"""

from __future__ import annotations

import numpy as np

from .catalogue import Accepted, CatalogueEffect, Columns, Linearised, Role
from .finding import Finding
from .model import SOFT_BASIS

EFFECT = "soft_iron"
MIN_GAIN_DEVIATION = 0.0025  # practical floor: 0.25 % of gain
# a soft-iron direction is determined by the data when its gain is pinned to 1 % (1σ, the limit
# magcal.fit puts on an ellipsoid's shape) and its columns keep a tenth of their length once
# offset and radius are fitted: below that the gain trades with the offset along a flat valley
# (a level band of directions pins the vertical gain only through the tilt), where a nonlinear
# fit can slide far off
MAX_GAIN_SIGMA = 0.01
MIN_UNIQUE = 0.1


def regressors(m: np.ndarray, offset_ut: np.ndarray) -> np.ndarray:
    """(n, 5): ∂|h|/∂s_p = uᵀE_p d at the sphere's own point R·u (R the mean radius), not at
    the measurement d: the measured |d| carries the noise along the field, which the radial
    residual carries too, and a regressor holding the residual's own noise is correlated with
    it — its coefficient is biased and, its unique part being small on partial coverage, its
    information overstated."""
    d = m - offset_ut
    rho = np.linalg.norm(d, axis=1, keepdims=True)
    u = d / rho
    return float(np.mean(rho)) * np.stack([np.einsum("ij,jk,ik->i", u, e_p, u) for e_p in SOFT_BASIS], axis=1)


def determined_directions(m: np.ndarray, offset_ut: np.ndarray, sigma_ut: float) -> np.ndarray:
    """(5, k): the combinations of SOFT_BASIS the data determine about this offset, judged on
    the data's own information: the soft-iron block of the information matrix once offset and
    radius are fitted (its Schur complement), whose eigenvectors are the directions and whose
    eigenvalues give each direction's 1σ of gain for residual σ ``sigma_ut``."""
    d = m - offset_ut
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    base = np.concatenate([-u, -np.ones((len(m), 1))], axis=1)
    soft = regressors(m, offset_ut)
    g_bb, g_bs, g_ss = base.T @ base, base.T @ soft, soft.T @ soft
    schur = g_ss - g_bs.T @ np.linalg.solve(g_bb, g_bs)
    lam, vec = np.linalg.eigh(0.5 * (schur + schur.T))
    share = lam / np.maximum(vec.T**2 @ np.diag(g_ss), 1e-300)  # squared unique fraction of each direction
    ok = (share >= MIN_UNIQUE**2) & (sigma_ut / np.sqrt(np.maximum(lam, 1e-300)) <= MAX_GAIN_SIGMA)
    return vec[:, ok]


def fitted_size(x_soft: np.ndarray, soft_dirs: np.ndarray, ref) -> tuple[float, float]:
    """The size of the soft iron ``ref`` carries (a ModelFit): the RMS of its radial signature
    (µT) through the soft-iron columns ``x_soft`` (n, k) along ``soft_dirs`` (5, k), and its
    largest relative gain deviation. (0, 0) when it carries none."""
    if not ref.spec.soft_iron or x_soft.shape[1] == 0:
        return 0.0, 0.0
    coords = np.linalg.lstsq(soft_dirs, ref.soft, rcond=None)[0]
    return float(np.sqrt(np.mean((x_soft @ coords) ** 2))), max_deviation(ref.soft_iron)


def gains(soft_iron: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's relative gains along its principal axes (eigen-decomposition of W⁻¹,
    normalised to a mean of 1) and those axes as columns."""
    g, v = np.linalg.eigh(np.linalg.inv(soft_iron))
    return g / g.mean(), v


def max_deviation(soft_iron: np.ndarray) -> float:
    g, _ = gains(soft_iron)
    return float(np.max(np.abs(g - 1.0)))


def describe(soft_iron: np.ndarray, evidence: dict) -> Finding:
    g, v = gains(soft_iron)
    hi, lo = int(np.argmax(g)), int(np.argmin(g))
    spread = 100.0 * (g[hi] - g[lo])
    dev = 100.0 * max_deviation(soft_iron)
    off = soft_iron - np.diag(np.diag(soft_iron))
    kind = "cross-axis coupling or non-orthogonal axes" if np.max(np.abs(off)) > 0.5 * np.max(
        np.abs(np.diag(soft_iron) - np.trace(soft_iron) / 3)
    ) else "different scale factors per axis"
    summary = (
        f"The sensor's gain depends on the field direction ({kind}): it reads {spread:.2f} % more "
        f"along {_axis(v[:, hi])} than along {_axis(v[:, lo])}, so the data lie on an ellipsoid "
        "that a sphere fit leaves as a two-cycle heading error."
    )
    return Finding(
        effect=EFFECT,
        summary=summary,
        where={
            "high_gain_direction": [float(x) for x in _sign(v[:, hi])],
            "low_gain_direction": [float(x) for x in _sign(v[:, lo])],
            "gain_spread_pct": float(spread),
        },
        evidence=evidence,
        params={
            "soft_iron": [[float(x) for x in row] for row in soft_iron],
            "principal_gains": [float(x) for x in g],
            "max_gain_deviation_pct": float(dev),
        },
    )


def _sign(v: np.ndarray) -> np.ndarray:
    return v if v[np.argmax(np.abs(v))] >= 0 else -v


def _axis(v: np.ndarray) -> str:
    v = _sign(v)
    names = "xyz"
    big = np.argsort(-np.abs(v))
    if abs(v[big[0]]) > 0.95:
        return f"the sensor {names[big[0]]} axis"
    return "the direction (" + ", ".join(f"{x:+.2f}" for x in v) + ")"


def columns(lin: Linearised) -> Columns:
    """The soft-iron group: the Jacobian's soft-iron columns at the reference (at the model's own
    point on the surface, design.linearise) along only the directions the data determine (the
    reference's, ``determined_directions``); along the others (``rest``) they are fitted beside
    every candidate but not tested. The reference's own soft iron is taken back out of the
    residual to first order, so the test is linearised where the model fits (design.build)."""
    jac, dirs = lin.jac_soft, lin.reference.spec.soft_matrix
    rest = jac @ np.linalg.svd(dirs, full_matrices=True)[0][:, dirs.shape[1] :]
    return Columns(jac @ dirs, ((EFFECT, dirs.shape[1]),), jac @ lin.reference.soft, rest, dirs)


def finding(acc: Accepted) -> Finding:
    """An accepted soft iron as a finding: the refitted matrix and its evidence."""
    return describe(acc.final.soft_iron, acc.evidence)


# a direction the other columns largely mimic is left out of the test (MIN_UNIQUE): along such a
# direction the gain trades with offset and radius, and its second-order residue would pass for a signal
TERM = CatalogueEffect(EFFECT, Role.TESTED, columns, finding, MIN_UNIQUE)
