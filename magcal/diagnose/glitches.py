"""Glitches: isolated jumps of the field 3-vector that the motion cannot explain.

A glitch perpendicular to the field barely changes |m| (physics.md), so the radial residual
cannot see it; the smoothness of the trajectory can. Each sample is predicted from its two
neighbours by cubic (Lagrange) interpolation from two samples on each side; the innovation d_i = m_i − prediction is scaled
per axis by a robust (MAD) scale of the data's own innovations, taken locally (motion speed
and sample rate differ between recordings) and never below the quantisation step. The squared
scaled innovation is referred to χ²(3) with a Bonferroni threshold over the samples. Flagged
samples are removed one cluster peak at a time (a glitch also disturbs its neighbours'
predictions), repaired by interpolation, and the innovations recomputed. A flagged sample must
also stand off the linear trend from its left and from its right (a glitch jumps and comes
back; a level step or a fast swing agrees with one side), and bursts of flags are fast motion.
Neighbours are taken on the nominal sample grid, not the logged timestamps (logging jitters).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

_LOCAL = 128  # samples per block of the local scale
_TRIM = 0.9  # the scale is the RMS of the central 90 % of |d| …
_TRIM_C = 0.7893  # … divided by √E[Z² | |Z| ≤ 1.645] for a Gaussian Z


@dataclass(frozen=True)
class Glitches:
    index: np.ndarray  # positions in the analysed series
    z: np.ndarray  # scaled innovation norm of each
    jump_ut: np.ndarray  # innovation vector length, µT
    threshold_z: float
    noise_ut: float  # robust white-noise σ per axis implied by the innovations


def _weights(t: np.ndarray) -> np.ndarray:
    """Lagrange weights predicting sample i from i−2, i−1, i+1, i+2 at t_i (cubic: motion
    curvature cancels). Rows for the interior samples 2 … n−3; uniform weights
    (−1, 4, 4, −1)/6 where timestamps repeat or go backwards."""
    tt = np.stack([t[:-4], t[1:-3], t[3:-1], t[4:]], axis=1)
    ti = t[2:-2]
    w = np.ones_like(tt)
    ok = np.ones(len(ti), bool)
    for j in range(4):
        for k in range(4):
            if k == j:
                continue
            den = tt[:, j] - tt[:, k]
            ok &= np.abs(den) > 1e-12
            w[:, j] *= (ti - tt[:, k]) / np.where(np.abs(den) > 1e-12, den, 1.0)
    ok &= np.all(np.isfinite(w), axis=1) & (np.abs(w).max(axis=1) < 10)
    w[~ok] = np.array([-1, 4, 4, -1]) / 6.0
    return w


def innovations(m: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """m − (prediction from the two neighbours on each side), and the noise-variance gain
    1 + Σw² of that difference (1.944 for uniform sampling)."""
    n = len(m)
    d = np.zeros_like(m)
    if n < 5:
        return d, 1.0
    w = _weights(t)
    pred = w[:, 0:1] * m[:-4] + w[:, 1:2] * m[1:-3] + w[:, 2:3] * m[3:-1] + w[:, 3:4] * m[4:]
    d[2:-2] = m[2:-2] - pred
    # the two samples at each end: linear extrapolation from the next two inside
    d[0] = m[0] - (2 * m[1] - m[2])
    d[1] = m[1] - 0.5 * (m[0] + m[2])
    d[-2] = m[-2] - 0.5 * (m[-1] + m[-3])
    d[-1] = m[-1] - (2 * m[-2] - m[-3])
    return d, float(1.0 + np.mean(np.sum(w * w, axis=1)))


def _quantum(m: np.ndarray) -> np.ndarray:
    q = np.empty(3)
    for a in range(3):
        diff = np.abs(np.diff(m[:, a]))
        nz = diff[diff > 1e-9]
        q[a] = np.percentile(nz, 1) if len(nz) else 1e-3
    return q


def trimmed_scale(d: np.ndarray, axis: int = 0) -> np.ndarray:
    """Robust σ of innovations along ``axis``: a trimmed RMS (quantised data make the MAD snap
    to the count lattice; a trimmed RMS does not)."""
    ad = np.abs(d)
    q = np.expand_dims(np.quantile(ad, _TRIM, axis=axis), axis)
    inside = ad <= q
    ms = np.sum(np.where(inside, ad * ad, 0.0), axis=axis) / np.maximum(inside.sum(axis=axis), 1)
    return np.sqrt(ms) / _TRIM_C


def local_scale(d: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """Per-sample, per-axis robust scale of innovations over blocks of _LOCAL samples,
    max'ed with neighbouring blocks, never below half the global scale or the floor."""
    n = len(d)
    nb = max(1, n // _LOCAL)
    glob = trimmed_scale(d)
    if nb == 1:
        blk = glob[None]
    else:
        blk = trimmed_scale(d[: nb * _LOCAL].reshape(nb, _LOCAL, 3), axis=1)
    if nb >= 3:  # max with the neighbours: a block boundary inside a fast swing stays covered
        pad = np.vstack([blk[:1], blk, blk[-1:]])
        blk = np.maximum(np.maximum(pad[:-2], pad[1:-1]), pad[2:])
    blk = np.maximum(blk, np.maximum(0.5 * glob, floor))
    which = np.minimum(np.arange(n) // _LOCAL, nb - 1)
    return blk[which]


def sample_grid(t: np.ndarray) -> np.ndarray:
    """Sample positions in units of the nominal sample interval. A sensor samples at a fixed
    rate and logging jitters the timestamps, so neighbours are neighbours; only gaps (dropped
    samples, > 1.5 intervals) count as missing positions."""
    n = len(t)
    if n < 3:
        return np.arange(n, dtype=np.float64)
    dt = np.diff(t)
    med = np.median(dt[dt > 0]) if np.any(dt > 0) else 0.0
    if not med > 0:
        return np.arange(n, dtype=np.float64)
    steps = np.where(dt > 1.5 * med, np.round(dt / med), 1.0)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _one_sided(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Innovations against linear extrapolation from the two samples on the left and on the
    right (noise-variance gain 6 each)."""
    left = np.zeros_like(m)
    right = np.zeros_like(m)
    left[2:] = m[2:] - (2 * m[1:-1] - m[:-2])
    right[:-2] = m[:-2] - (2 * m[1:-1] - m[2:])
    return left, right


def _z(d: np.ndarray, floor: np.ndarray) -> np.ndarray:
    return np.sqrt(np.sum((d / local_scale(d, floor)) ** 2, axis=1))


def detect(m: np.ndarray, t: np.ndarray, alpha: float = 0.01, max_rounds: int = 8) -> Glitches:
    m = np.array(m, dtype=np.float64, copy=True)
    n = len(m)
    g = sample_grid(np.asarray(t, np.float64))
    floor = 0.5 * _quantum(m) if n > 3 else np.full(3, 1e-3)
    d, gain = innovations(m, g)
    noise = float(np.median(trimmed_scale(d)) / np.sqrt(gain)) if n else 0.0
    thr = float(np.sqrt(stats.chi2.isf(alpha / max(n, 1), 3))) if n else np.inf
    side_thr = float(np.sqrt(stats.chi2.isf(alpha, 3)))
    flagged = np.zeros(n, bool)
    zs = np.zeros(n)
    jumps = np.zeros(n)
    for _ in range(max_rounds):
        z = _z(d, floor)
        z[flagged] = 0
        over = z > thr
        if not over.any():
            break
        # peaks: larger than both neighbours within ±2 samples
        zp = np.pad(z, 2)
        peak = over.copy()
        for s in (1, 2):
            peak &= z >= zp[2 - s : 2 - s + n]
            peak &= z >= zp[2 + s : 2 + s + n]
        # isolated: off the trend from the left AND from the right (a step or a fast swing
        # agrees with one side; a glitch jumps and comes back)
        left, right = _one_sided(m)
        peak &= np.minimum(_z(left, floor), _z(right, floor)) > side_thr
        idx = np.flatnonzero(peak)
        if len(idx) == 0:
            break
        flagged[idx] = True
        zs[idx] = z[idx]
        jumps[idx] = np.linalg.norm(d[idx], axis=1)
        good = np.flatnonzero(~flagged)
        if len(good) < 3:
            break
        for a in range(3):  # repair by interpolation from unflagged samples
            m[idx, a] = np.interp(g[idx], g[good], m[good, a])
        d, _ = innovations(m, g)
    # bursts (three or more flags within five samples) are fast motion, not glitches
    if flagged.any():
        c = np.convolve(flagged.astype(int), np.ones(5, int), mode="same")
        burst = np.convolve((c >= 3).astype(int), np.ones(5, int), mode="same") > 0
        flagged &= ~burst
    idx = np.flatnonzero(flagged)
    return Glitches(idx, zs[idx], jumps[idx], thr, noise)
