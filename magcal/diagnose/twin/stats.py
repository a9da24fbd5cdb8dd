"""The statistics of a residual that tell a real recording from its twin (numerics only).

Every statistic is computed the same way on the real recording and on each twin draw, after
refitting the same calibration model to it: e = |h| − r the radial residual, u the field
direction, m the measurements, t the times. ``battery`` returns one value per statistic and
the located pieces (per time block, per direction cell, per channel) that say where a
mismatch sits.

| name | what | physics it answers to |
|---|---|---|
| rms_ut | RMS of e: the |field| spread | noise, any unmodelled error |
| tail_ratio | 99th over 50th percentile of |e| | glitches, intermittent disturbances, the noise law |
| lag1 | lag-1 autocorrelation of e | slow wander, a sensor's own filter |
| slow_share | variance share left in a 1 s moving average of e | slow wander |
| block_wander_ut | RMS spread of the offset fitted per time block | offset wander, steps |
| psd_slope | log-log slope of e's spectrum at 0.02–1 Hz | the wander's spectrum |
| harmonic_share | share of var(e) in degree-3/4 direction terms | direction nonlinearity |
| gain_deviation | largest relative gain of a free ellipsoid fit | soft iron, scale mismatch |
| direction_bias_ut | RMS of e's mean over 20 direction cells | any direction-dependent error |
| glitch_rate | share of isolated jumps in the 3-vector trajectory | glitches |
| repeat_share | share of reads equal to the one before on every axis (only where the recording has any) | repeated reads |
| xcorr:<channel> | largest |correlation| of e with the channel (±2 s) | channel coupling |

The 1 s smoothing, the ±2 s lags and psd_slope's 0.02–1 Hz band are seconds and hertz; on a
recording without a clock (its t the sample index) they keep the ratio the step search's windows
keep (locate.steps_rest.window), not 1 and 2 samples and 0.02–1 cycles per sample.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from ...sim import directions
from .. import timewords
from ..locate.base import repeats
from ..locate.steps import half_window_s
from ..locate.steps_rest import window

N_BLOCKS = 20
N_CELLS = 20
MIN_CELL = 10
JUMP_Z = 8.0
LOCAL = 25
XCORR_LAG_S = 2.0
SMOOTH_S = 1.0


def cell_centres(k: int = N_CELLS) -> np.ndarray:
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    phi = np.pi * (1 + 5**0.5) * i
    s = np.sqrt(1 - z * z)
    return np.column_stack([s * np.cos(phi), s * np.sin(phi), z])


_CELLS = cell_centres()


def cells_of(u: np.ndarray) -> np.ndarray:
    return np.argmax(u @ _CELLS.T, axis=1)


def dt_of(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 1.0


def tail_ratio(e: np.ndarray) -> float:
    """The 99th over the 50th percentile of |e − median(e)|: 3.82 for Gaussian e."""
    ae = np.abs(e - np.median(e))
    return float(np.quantile(ae, 0.99) / max(np.quantile(ae, 0.5), 1e-12))


def lag1(e: np.ndarray) -> float:
    x = e - e.mean()
    den = float(x @ x)
    return float(x[:-1] @ x[1:]) / den if den > 0 else 0.0


def moving_average(x: np.ndarray, width: int) -> np.ndarray:
    if width <= 1:
        return x.copy()
    c = np.concatenate([[0.0], np.cumsum(x)])
    half = width // 2
    lo = np.clip(np.arange(len(x)) - half, 0, len(x))
    hi = np.clip(np.arange(len(x)) + width - half, 0, len(x))
    return (c[hi] - c[lo]) / (hi - lo)


def slow_share(e: np.ndarray, dt: float, smooth: float = SMOOTH_S) -> float:
    """The variance share left in a moving average over ``smooth`` (in the units of t)."""
    x = e - e.mean()
    v = float(np.var(x))
    return float(np.var(moving_average(x, int(round(smooth / dt))))) / v if v > 0 else 0.0


def block_offsets(e: np.ndarray, u: np.ndarray, n_blocks: int = N_BLOCKS) -> np.ndarray:
    """(B, 4): per contiguous time block, the radial level and offset vector (ridge-stabilised
    least squares of e on [1, u])."""
    out = []
    for idx in np.array_split(np.arange(len(e)), n_blocks):
        if len(idx) < 8:
            continue
        x = np.column_stack([np.ones(len(idx)), u[idx]])
        a = x.T @ x + 1e-2 * len(idx) * np.diag([0.0, 1, 1, 1])
        out.append(np.linalg.solve(a, x.T @ e[idx]))
    return np.array(out).reshape(-1, 4)


def block_wander(e: np.ndarray, u: np.ndarray) -> float:
    b = block_offsets(e, u)
    if len(b) < 2:
        return 0.0
    d = b[:, 1:] - np.median(b[:, 1:], axis=0)
    return float(np.sqrt(np.mean(d * d)))


PSD_BAND_HZ = (0.02, 1.0)


def psd_slope(e: np.ndarray, dt: float, band=PSD_BAND_HZ) -> float:
    fs = 1.0 / dt
    duration = len(e) * dt
    lo = max(band[0], 4.0 / duration)
    hi = min(band[1], 0.25 * fs)
    if hi <= 2 * lo:
        lo, hi = 4.0 / duration, 0.25 * fs
    nper = int(min(len(e), max(16, 2.0 / lo * fs)))
    f, p = signal.welch(e - e.mean(), fs=fs, nperseg=nper)
    sel = (f >= lo) & (f <= hi) & (p > 0)
    if np.count_nonzero(sel) < 3:
        return 0.0
    return float(np.polyfit(np.log(f[sel]), np.log(p[sel]), 1)[0])


def harmonic_share(e: np.ndarray, u: np.ndarray) -> float:
    """Share of e (beyond degree ≤ 2 in the direction) that degree-3/4 terms explain."""
    low = np.column_stack([np.ones(len(u)), u, u[:, [0, 0, 1]] * u[:, [1, 2, 2]], u[:, :2] ** 2])  # z² = 1 − x² − y²
    q, r = np.linalg.qr(np.column_stack([low, directions.basis(u)]))
    d = np.abs(np.diag(r))
    if d.min() < 1e-6 * d.max():
        return float("nan")  # the directions do not span the degree-4 functions
    z = q.T @ e
    k = low.shape[1]
    rest = float(e @ e) - float(z[:k] @ z[:k])
    return float(z[k:] @ z[k:]) / rest if rest > 0 else 0.0


def cell_means(e: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Mean residual per direction cell (NaN where fewer than MIN_CELL samples)."""
    c = cells_of(u)
    counts = np.bincount(c, minlength=N_CELLS)
    sums = np.bincount(c, weights=e - e.mean(), minlength=N_CELLS)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts >= MIN_CELL, sums / np.maximum(counts, 1), np.nan)


def direction_bias(cells: np.ndarray) -> float:
    ok = np.isfinite(cells)
    return float(np.sqrt(np.mean(cells[ok] ** 2))) if ok.any() else 0.0


def jumps(m: np.ndarray) -> np.ndarray:
    """Samples that jump away from both neighbours: the second difference on some axis above
    JUMP_Z times its local typical size (a running mean over ±LOCAL samples, so a fast but
    smooth motion is not a jump), the largest of a run only."""
    if len(m) < 5:
        return np.zeros(len(m), bool)
    d2 = np.abs(m[2:] - 2 * m[1:-1] + m[:-2])
    local = np.column_stack([moving_average(d2[:, a], 2 * LOCAL + 1) for a in range(3)])
    floor = np.maximum(np.median(d2, axis=0), 1e-9)
    z = np.max(0.798 * d2 / np.maximum(local, floor), axis=1)  # mean |N(0, σ)| = 0.798 σ
    hit = np.zeros(len(m), bool)
    hit[1:-1] = (z > JUMP_Z) & (z >= np.roll(z, 1)) & (z >= np.roll(z, -1))
    return hit


def xcorr_max(e: np.ndarray, x: np.ndarray, dt: float, max_lag: float = XCORR_LAG_S) -> tuple[float, float]:
    """(largest |corr(e, x shifted)|, its lag in the units of t) over ±``max_lag``."""
    a, b = e - e.mean(), x - x.mean()
    den = np.sqrt(float(a @ a) * float(b @ b))
    if den <= 0:
        return 0.0, 0.0
    n = len(a)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    cc = np.fft.irfft(np.fft.rfft(a, size) * np.conj(np.fft.rfft(b, size)), size)
    k = min(int(max_lag / dt), n - 1)
    lags = np.concatenate([np.arange(0, k + 1), np.arange(-k, 0)])
    vals = cc[lags] / den
    j = int(np.argmax(np.abs(vals)))
    return float(abs(vals[j])), float(lags[j] * dt)


def gain_deviation(m: np.ndarray) -> float:
    from ...fit.ellipsoid import fit_ellipsoid

    f = fit_ellipsoid(m, kind="full")
    if not f:
        return float("nan")
    return gain_of(f.soft_iron)


def gain_of(soft_iron: np.ndarray) -> float:
    w = np.linalg.eigvalsh(np.asarray(soft_iron))
    return float(np.max(np.abs(w / np.mean(w) - 1.0)))


def battery(e, u, m, t, channels, gain: float | None = None, with_repeats: bool = False) -> tuple[dict, dict]:
    """(statistics by name, located pieces: block levels, cell means, channel lags).

    ``with_repeats``: also the share of repeated reads — asked only where the recording has
    any (a host polling faster than its sensor converts); elsewhere it would be 0 against 0."""
    dt = dt_of(t)
    clock = timewords.clocked()
    half = half_window_s(t, clock) if len(t) > 1 else 1.0
    stats = {
        "rms_ut": float(np.sqrt(np.mean(e * e))),
        "tail_ratio": tail_ratio(e),
        "lag1": lag1(e),
        "slow_share": slow_share(e, dt, window(SMOOTH_S, half, clock)),
        "block_wander_ut": block_wander(e, u),
        "psd_slope": psd_slope(e, dt, tuple(f / window(1.0, half, clock) for f in PSD_BAND_HZ)),
        "harmonic_share": harmonic_share(e, u),
        "direction_bias_ut": 0.0,
        "glitch_rate": float(np.mean(jumps(m))),
    }
    cells = cell_means(e, u)
    stats["direction_bias_ut"] = direction_bias(cells)
    stats["gain_deviation"] = gain_deviation(m) if gain is None else float(gain)
    if with_repeats:
        stats["repeat_share"] = float(np.mean(repeats(m)))
    lags = {}
    for name, x in channels.items():
        stats["xcorr:" + name], lags[name] = xcorr_max(e, x, dt, window(XCORR_LAG_S, half, clock))
    blocks = np.array([float(np.mean(b)) for b in np.array_split(e - e.mean(), N_BLOCKS) if len(b)])
    return stats, {"blocks": blocks, "cells": cells, "lags": lags}
