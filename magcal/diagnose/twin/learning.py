"""Learning a recording's SensorModel around a calibration (``learn``): per-axis noise and its
law, the quantum, glitches, direction nonlinearity and a temperature gain when held-out time blocks
confirm them, disturbances, saturation, repeated reads, takes, and the offset and field
wander as a fitted spectrum (``magcal.sim.wander.fit``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping

import numpy as np

from ...core.calibration import Calibration
from ...core.series import Series
from ...sim import directions
from ...sim import wander as wander_mod
from ...sim.model import TEMP, SensorModel, replace_calibration
from ...sim.takes import Takes
from ..lattice import quantum
from . import takes as takes_mod
from .draw import twin_directions, twin_draw
from .events import disturbances
from .glitch_rate import along_the_field, glitch_process
from .noise import less_noise, noise_lag1, noise_law, repeat_share
from .residual import corrected, refit, refit_projector, with_time
from .spikes import find_glitches, glitch_train


FOLDS = 5
BLOCKS = 40
CV_GAIN = 0.01  # a term must cut the held-out residual energy by at least 1 %


def _heldout_gain(e: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Coefficients of e on the columns of x (all data) and the held-out share of residual
    energy they remove: FOLDS folds of interleaved time blocks (BLOCKS blocks), so every fold
    sees most directions while the slow wander stays within a block."""
    n = len(e)
    fold = (np.arange(n) * BLOCKS // max(n, 1)) % FOLDS
    sse0 = sse1 = 0.0
    for k in range(FOLDS):
        idx = fold == k
        train = ~idx
        c = np.linalg.lstsq(x[train], e[train], rcond=None)[0]
        r = e[idx] - x[idx] @ c
        sse0 += float(e[idx] @ e[idx])
        sse1 += float(r @ r)
    coef = np.linalg.lstsq(x, e, rcond=None)[0]
    return coef, (sse0 - sse1) / max(sse0, 1e-300)


def _axis_noise(m: np.ndarray, white_var: float, u: np.ndarray, q: tuple) -> tuple:
    """Per-axis white noise: its shape from the second differences of the trajectory, its
    level from the white part of the radial residual, less the quantisation's share. ``u``:
    per sample, how a departure of the raw reading shows in the radial residual (Wᵀu)."""
    d2 = m[2:] - 2 * m[1:-1] + m[:-2]
    shape = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) * 1.4826 / np.sqrt(6.0)
    shape = np.where(shape > 0, shape, max(float(shape.max()), 1e-6))
    quant = np.asarray(q) ** 2 / 12.0
    radial_shape = float(np.mean(u * u @ (shape**2)))
    radial_quant = float(np.mean(u * u @ quant))
    level = max(white_var - radial_quant, 0.0) / max(radial_shape, 1e-300)
    return tuple(float(v) for v in shape * np.sqrt(level))


def _saturation(m: np.ndarray) -> float | None:
    top = np.max(np.abs(m))
    at_rail = np.isclose(np.abs(m), top, rtol=0, atol=1e-9 + 1e-6 * top)
    return float(top) if np.count_nonzero(at_rail) >= max(5, 0.002 * len(m)) else None


def learn(series: Series, calibration: Calibration, source: Mapping | None = None, free: bool = True) -> SensorModel:
    """The SensorModel of ``series`` around ``calibration`` (its deterministic part).
    ``free=False``: the calibration came from elsewhere and the motion cannot determine one
    (a still board); direction terms are not sought and the refit only removes the level.
    A recording of takes (``placements``) is learned again with a level per take removed."""
    model = _learn(series, calibration, source, free)
    takes = placements(model, series.only_valid(), free)
    return model if takes is None else _learn(series, calibration, source, free, takes)


TAKE_SEEDS = tuple(range(201, 209))


def placements(model: SensorModel, series: Series, free: bool = True) -> Takes | None:
    """The takes of a recording (``takes``) when its level steps at their starts more than
    the twins of ``model`` (learned without takes) step there, with the spread of its levels
    between them; else None."""
    real = refit(model, series.field_ut, series.t_s, with_time(series), free)
    takes = None if real is None else takes_mod.candidate(real.u, real.t)
    if takes is None:
        return None
    u = twin_directions(model, series)
    twins = [twin_draw(model, series, seed, free, u) for seed in TAKE_SEEDS]
    steps = [takes_mod.level_steps(x.e, x.t, takes) for x in twins if x is not None]
    if not takes_mod.steps_exceed(takes_mod.level_steps(real.e, real.t, takes), steps):
        return None
    return takes_mod.with_levels(takes, real.e, real.t)


def _learn(series: Series, calibration: Calibration, source: Mapping | None, free: bool,
           takes: Takes | None = None) -> SensorModel:
    """``learn`` with the takes given (None: one take)."""
    s = series.only_valid()
    m, t, chans = s.field_ut, s.t_s, with_time(s)
    q = quantum(m)
    h_all = corrected(calibration, m, chans)
    r_all = np.linalg.norm(h_all, axis=1)
    u_all = h_all / r_all[:, None]
    seen_all = u_all @ np.asarray(calibration.soft_iron)  # how a jump of the reading moves |h|
    rate, size, axis_share, hit = find_glitches(m, r_all, seen_all, u_all)
    keep = ~hit
    used = {c: chans[c][keep] for c in calibration.coef_ut_per_unit}
    h = calibration.correct(m[keep], used)
    r = np.linalg.norm(h, axis=1)
    u = h / r[:, None]
    e = r - calibration.field_ut
    e = e - e.mean()
    e = e if takes is None else takes.demean(e, t[keep])  # each placement's level is its calibration's
    nonlin = np.zeros(len(directions.NAMES))
    coef, gain = _heldout_gain(e, directions.basis(u)) if free else (nonlin, 0.0)
    if gain > CV_GAIN:
        nonlin = coef
        e = e - directions.basis(u) @ coef
    temp_gain, temp_ref = 0.0, 25.0
    if TEMP in chans:
        temp_ref = float(np.median(chans[TEMP]))
        x = ((chans[TEMP][keep] - temp_ref) * calibration.field_ut)[:, None]
        c, g = _heldout_gain(e, x)
        if g > CV_GAIN:
            temp_gain, e = float(c[0]), e - x[:, 0] * float(c[0])
    dist, _, e = disturbances(e, t[keep])  # the wander is fitted with each replaced by its level
    e = e - e.mean()
    # the noise, the quantum and the offset wander enter the raw reading, which the residual
    # sees through the soft iron: |W(m − b)| moves by (Wᵀu)·δ for a departure δ of m
    seen = u @ np.asarray(calibration.soft_iron)
    comps, white = wander_mod.fit(e, seen, t[keep], refit_projector(u, used, takes, t[keep], free))
    model = SensorModel(
        calibration=replace_calibration(calibration, field_ut=calibration.field_ut + float(np.mean(r - calibration.field_ut))),
        noise_ut=_axis_noise(m[keep], white, seen, q), quantum_ut=q, wander=comps,
        glitch_rate=rate, glitch_ut=size, glitch_axis_share=axis_share, **glitch_train(t[hit], wander_mod.sample_interval(t)),
        disturbances=dist, nonlinearity_ut=tuple(nonlin),
        temp_gain_per_c=temp_gain, temp_ref_c=temp_ref, saturation_ut=_saturation(m), takes=takes,
        rate_hz=1.0 / wander_mod.sample_interval(t), source=dict(source or {}),
    )
    model = replace(model, repeat_share=repeat_share(model, s))
    if rate > 0:
        rate, missed = glitch_process(model, s, hit)
        glitched, missed = along_the_field(replace(model, glitch_rate=rate), s, hit, h_all, missed,
                                           lambda share: find_glitches(m, r_all, seen_all, u_all, share)[1])
        model = replace(glitched, noise_ut=less_noise(model, s, missed))
    model = replace(model, noise_lag1=noise_lag1(model, s, free))
    model = replace(model, noise_law=noise_law(model, s, free))
    # once more with the final glitches and noise: both set how many reads repeat by chance and
    # how many of the model's repeats a glitch breaks (learned before them, the twins of rm3100
    # estibone test0 repeated 0.213–0.218 of their reads against the recording's 0.236)
    return replace(model, repeat_share=repeat_share(model, s))
