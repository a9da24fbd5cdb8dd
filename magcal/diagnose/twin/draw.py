"""Twins of a recording: its field directions through the model's inverse, the twin's reads
along them (its own noise, wander, glitches and repeats), and a twin refitted as the
recording is.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping

import numpy as np

from ...core.series import Series
from ...sim.model import Draws, SensorModel
from .residual import RefitResidual, radius, refit, with_time
from .spikes import spikes
from .stats import repeats


def twin_directions(model: SensorModel, series: Series) -> np.ndarray:
    """The field directions (n, 3) behind a recording, through the model's inverse, with each
    glitch sample re-drawn between the directions around it (the twin draws its own glitches;
    replayed, they would be there twice). When the model repeats reads, each of the
    recording's repeated reads keeps the direction of the read it repeats, bit for bit: the
    reads whose direction differs from the one before are the recording's conversions, which
    the twin replays one for one in its own pattern of repeats (``replayed``)."""
    chans = with_time(series)
    m = series.field_ut
    u = model.directions_of(m, {c: chans[c] for c in model.calibration.coef_ut_per_unit})
    bad = spikes(m, radius=radius(model.calibration, m, chans), directions=u)
    again = repeats(m) if model.repeat_share > 0 else np.zeros(len(m), bool)
    bad &= ~again
    good = np.flatnonzero(~(bad | again))
    if bad.any() and len(good) >= 2:
        k = np.flatnonzero(bad)
        v = np.column_stack([np.interp(k, good, u[good, a]) for a in range(3)])
        u[k] = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    if again.any():
        u = u[np.maximum.accumulate(np.where(again, 0, np.arange(len(m))))]
    return u


def replayed(u: np.ndarray, shown: np.ndarray | None) -> np.ndarray:
    """The direction each of a twin's reads sees when the twin replays the recording's
    conversions one for one: ``u`` the recording's directions per read (``twin_directions``:
    a repeated read has the direction before it, bit for bit), ``shown`` the read whose
    conversion each of the twin's reads shows (``Draws.shown``; None: every read a conversion
    of its own, ``u`` as it is). The recording's reads less its own repeats are its sequence of
    conversions; the twin's conversions take them in order — a read the twin repeats re-reads
    the conversion before, and the next takes the next of the recording's, not the one two on
    (the steady turn of a board steps as far between conversions as the recording's do). The
    two counts differ a little (the repeats a still board or a coarse quantum make by chance
    are not in the model's share): the twin's conversion c takes the recording's nearest
    c·(C_rec − 1)/(C_twin − 1), never a direction between two (no chord across a pause)."""
    if shown is None or len(u) < 2:
        return u
    fresh = np.flatnonzero(~repeats(u))  # the recording's conversions
    conv = np.cumsum(shown == np.arange(len(shown))) - 1  # the twin's conversion at each read
    k = np.rint(conv * ((len(fresh) - 1) / max(int(conv[-1]), 1))).astype(np.int64)
    return u[fresh[k]]


def twin_draws(model: SensorModel, u: np.ndarray, t: np.ndarray, seed: int) -> tuple[np.ndarray, Draws]:
    """(the direction each read sees, the random parts) of a twin driven along the
    recording's directions ``u``, its conversions ``replayed`` in the twin's pattern of
    repeats. Those directions came through the inverse model from the recording's readings,
    so they already carry the part of its white noise and offset wander that lies across the
    field (the inverse keeps it, only |h| is normalised away); the twin draws those two along
    the field alone — the gradient of |W(m − b)|, Wᵀu — or the part across the field would be
    there twice and the twin's trajectory rougher than the recording's (its jumps then hide
    among the noise)."""
    d = model.draws(t, seed)
    u = replayed(u, d.shown)
    v = u @ np.asarray(model.calibration.soft_iron)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    sigma = np.asarray(model.noise_ut)
    along = np.sum(d.noise * sigma * v, axis=1, keepdims=True) * v
    noise = np.where(sigma > 0, along / np.where(sigma > 0, sigma, 1.0), 0.0)
    wander = np.sum(d.wander_ut * v, axis=1, keepdims=True) * v
    return u, replace(d, noise=noise, wander_ut=wander)


def twin_readings(model: SensorModel, u: np.ndarray, t: np.ndarray, chans: Mapping, seed: int):
    """(m, valid): ``model``'s twin along the recording's directions ``u`` (``twin_draws``)."""
    seen, draws = twin_draws(model, u, t, seed)
    return model.distort(seen, chans, draws)


def twin_draw(model: SensorModel, series: Series, seed: int, free: bool = True, u=None) -> RefitResidual | None:
    """One twin of ``series`` refitted: the recording's times, channels and directions
    (``twin_directions``, or ``u`` when given)."""
    chans = with_time(series)
    u = twin_directions(model, series) if u is None else u
    m, valid = twin_readings(model, u, series.t_s, chans, seed)
    if not valid.all():
        m, chans = m[valid], {k: v[valid] for k, v in chans.items()}
    return refit(model, m, series.t_s[valid], chans, free)
