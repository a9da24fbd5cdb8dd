"""A recording (real or twin) seen through a refitted calibration: the residual every
comparison reads, and the linearised refit (``projector``) the wander is fitted through.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ...core.calibration import Calibration
from ...core.series import Series
from ...fit.ellipsoid import fit_ellipsoid
from ...fit.sphere import fit_sphere
from ...sim.model import SensorModel
from . import stats as ts
from ..model import Spec, fit_model


@dataclass(frozen=True)
class RefitResidual:
    """One recording (real or twin) seen through a calibration refitted to it (locate's
    ``Residual`` is a recording seen through the calibration diagnose returned)."""

    e: np.ndarray
    u: np.ndarray
    m: np.ndarray
    t: np.ndarray
    channels: Mapping[str, np.ndarray]
    gain: float | None = None


def _isotropic(w: np.ndarray) -> bool:
    return bool(np.max(np.abs(w / np.cbrt(np.linalg.det(w)) - np.eye(3))) < 1e-9)


def refit(model: SensorModel, m, t, channels, free: bool = True) -> RefitResidual | None:
    """Refit ``model``'s kind of calibration (sphere or ellipsoid, with its channel terms) to
    the measurements and return their residual; None when the fit fails. ``free=False`` keeps
    the model's calibration (a recording whose motion cannot determine one, e.g. a still board)
    and only removes the mean level. A recording of takes (``model.takes``) has a level per
    take removed as well: each placement's own hard-iron surroundings, part of its calibration."""
    cal = model.calibration
    if not free:
        h = cal.correct(m, {c: channels[c] for c in cal.coef_ut_per_unit})
        norm = np.linalg.norm(h, axis=1)
        e = norm - norm.mean() if model.takes is None else model.takes.demean(norm, t)
        return RefitResidual(e=e, u=h / norm[:, None], m=m, t=t, channels=channels, gain=None)
    soft = not _isotropic(cal.soft_iron)
    chans = tuple(cal.coef_ut_per_unit)
    used = {c: channels[c] for c in chans}
    if chans:
        f = fit_model(m, used, Spec(soft_iron=soft, channels=chans), cal.reference)
        if not f:
            return None
        fc = f.calibration()
        h = fc.correct(m, used)
        gain = ts.gain_of(fc.soft_iron) if soft else None
    else:
        f = fit_ellipsoid(m, kind="full") if soft else fit_sphere(m)
        if not f:
            return None
        h = (m - f.offset_ut) @ np.asarray(f.soft_iron).T
        gain = ts.gain_of(f.soft_iron) if soft else None
    norm = np.linalg.norm(h, axis=1)
    e = norm - np.sqrt(np.mean(norm * norm)) if chans else np.asarray(f.residual_ut)
    if model.takes is not None:
        e = model.takes.demean(e, t)
    return RefitResidual(e=e, u=h / norm[:, None], m=m, t=t, channels=channels, gain=gain)


def with_time(series: Series) -> dict:
    """The recording's channels, plus time (``t_s``) for a model with a drift term."""
    chans = dict(series.channels)
    chans.setdefault("t_s", series.t_s)
    return chans


def corrected(cal: Calibration, m: np.ndarray, chans: Mapping) -> np.ndarray:
    return cal.correct(m, {c: chans[c] for c in cal.coef_ut_per_unit})


def radius(cal: Calibration, m: np.ndarray, chans: Mapping) -> np.ndarray:
    return np.linalg.norm(corrected(cal, m, chans), axis=1)


def projector(u: np.ndarray, channels: Mapping[str, np.ndarray], then=None):
    """x ↦ what is left of a radial series x once a calibration is refitted: the residual of
    its least squares on the linearised model (offset, radius, soft iron: the degree ≤ 2
    functions of the direction; and x_c·u per channel term) — and then ``then`` of what is left
    (a level per take, ``Takes.demean``), in that order, as ``refit`` removes them."""
    cols = [np.ones(len(u)), *u.T, *(u[:, [0, 0, 1]] * u[:, [1, 2, 2]]).T, *(u[:, :2] ** 2).T]  # z² = 1 − x² − y²
    for x in channels.values():
        xc = x - np.mean(x)
        cols += [xc * u[:, a] for a in range(3)]
    q, _ = np.linalg.qr(np.column_stack(cols))

    def project(x: np.ndarray) -> np.ndarray:
        left = x - q @ (q.T @ x)
        return left if then is None else then(left)

    return project


def refit_projector(u: np.ndarray, channels: Mapping, takes, t: np.ndarray, free: bool):
    """What ``refit`` leaves of a radial series, linearised (``projector``; a fixed
    calibration removes only the level, per take when there are takes)."""
    per_take = None if takes is None else (lambda x: takes.demean(x, t))
    return projector(u, channels, per_take) if free else per_take
