"""A change point taken out with its own parameters fitted on the training blocks only.

The held-out judge (``judge``) refits the calibration without each time block and scores the
block it left out. A change point's ``remove`` uses parameters fitted on every sample — the
step's vector, or each side's own ellipsoid for a soft-iron change — so the block being scored
helped choose them, and on a short window whose coverage pins neither side well that alone can
make a change look better on "unseen" blocks (a 14 s window of a hand-held tilt take: held-out
RMS 0.41 → 0.29 µT with each side's ellipsoid fitted on every sample, 0.41 → 2.5 µT with them
fitted on the training blocks). These functions are the same removals with the parameters
fitted on ``train`` (a boolean mask) alone; where the training blocks hold too little of one
side to fit it, the samples are returned unchanged — that block cannot learn the change, and
gains nothing from it.
"""

from __future__ import annotations

import numpy as np

from ...fit import fit_calibration
from . import steps_scan as scan
from .base import Located

MIN_SIDE_TRAINED = 10  # samples of each side the training blocks must hold to fit the change


def _sides(t_s, located: Located, train: np.ndarray) -> tuple[np.ndarray, bool]:
    """(before τ, whether the training blocks hold enough of both sides)."""
    before = np.asarray(t_s, float) < float(located.params["time_s"])
    train = np.asarray(train, bool)
    enough = int(np.sum(before & train)) >= MIN_SIDE_TRAINED and int(np.sum(~before & train)) >= MIN_SIDE_TRAINED
    return before, enough


def remove_step_trained(m_ut, t_s, channels, located: Located, train: np.ndarray) -> np.ndarray:
    """The samples before the step shifted by a step fitted on ``train`` alone: one ellipsoid's
    shape for both sides, an offset for each (as ``steps.measure`` fits a step's vector)."""
    m = np.array(m_ut, dtype=np.float64, copy=True)
    before, enough = _sides(t_s, located, train)
    fit = fit_calibration(m[train], model="ellipsoid", reasons=False) if enough else None
    if not fit:
        return m
    cal = fit.calibration
    h = cal.correct(m[train])
    norm = np.linalg.norm(h, axis=1)
    u = h / norm[:, None]
    side = before[train][:, None]
    x = np.hstack([scan.quad(u, cal.field_ut), u * side, u * ~side])
    coef = scan.lsq(x, norm - cal.field_ut).coef
    m[before] += np.linalg.solve(cal.soft_iron, coef[9:12] - coef[6:9])
    return m


def remove_soft_trained(m_ut, t_s, channels, located: Located, train: np.ndarray) -> np.ndarray:
    """The samples before τ mapped through the ellipsoid fitted on ``train``'s samples before τ
    into the one fitted on ``train``'s samples after it (as ``steps.remove_soft``)."""
    m = np.array(m_ut, dtype=np.float64, copy=True)
    before, enough = _sides(t_s, located, train)
    fb = fit_calibration(m[before & train], model="ellipsoid", reasons=False) if enough else None
    fa = fit_calibration(m[~before & train], model="ellipsoid", reasons=False) if enough else None
    if not fb or not fa:
        return m
    cb, ca = fb.calibration, fa.calibration
    m[before] = ca.distort(cb.correct(m[before]) * (ca.field_ut / cb.field_ut))
    return m

