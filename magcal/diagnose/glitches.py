"""Glitches: isolated jumps of the field 3-vector that the motion cannot explain.

A glitch perpendicular to the field barely changes |m| (docs/physics.md, "Glitches"), so the radial residual
cannot see it; the smoothness of the trajectory can. Each sample is predicted from its two
neighbours by cubic (Lagrange) interpolation from two samples on each side; the innovation d_i = m_i − prediction is scaled
per axis by a robust (MAD) scale of the data's own innovations, taken locally (motion speed
and sample rate differ between recordings) and never below the quantisation step. The squared
scaled innovation is referred to χ²(3) with a Bonferroni threshold over the samples. Flagged
samples are removed one cluster peak at a time (a glitch also disturbs its neighbours'
predictions), repaired by interpolation, and the innovations recomputed; when repairing the
peak does not explain its neighbourhood but repairing a neighbour does, the neighbour is the
glitch (beside a gap in the timestamps a neighbour's prediction reaches across the gap and can
outscore the glitch's own). Each innovation is divided by its own prediction-noise gain. A flagged sample must
also stand off the linear trend from its left and from its right (a glitch jumps and comes
back; a level step or a fast swing agrees with one side), and bursts of flags are fast motion.
Neighbours are taken on the nominal sample grid, not the logged timestamps (logging jitters).

A second, radial channel watches |m − c| − r about a quick sphere fit. Rotation leaves |m|
unchanged, so this series stays smooth however fast the sensor turns, while the 3-vector's
innovations grow with the motion; on fast-moving recordings a glitch's radial part (half its
length on average) stands out there long before its 3-D jump does. Each channel gets half of
the Bonferroni budget, and a flagged sample must stand off both one-sided trends in the channel
that flagged it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..fit.failure import FitFailure
from ..fit.sphere import sphere_start
from ..fit.tails import chi2_isf
from .finding import Finding

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
    threshold_radial_z: float = float("inf")  # the radial channel's (inf: no sphere to watch)
    radial: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # flagged by the radial channel


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


def innovations(m: np.ndarray, t: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """m − (prediction from the two neighbours on each side) divided by the square root of
    its own noise-variance gain 1 + Σw² (1.944 for uniform sampling), and that gain per
    sample. Normalised so, a sample whose prediction reaches across a gap in the timestamps
    (large weights on a few neighbours) is not mistaken for a jump when one of those
    neighbours is the glitch. ``w``: ``_weights(t)`` when already made (they depend on the
    times alone)."""
    n = len(m)
    d = np.zeros_like(m)
    gain = np.ones(n)
    if n < 5:
        return d, gain
    w = _weights(t) if w is None else w
    pred = w[:, 0:1] * m[:-4] + w[:, 1:2] * m[1:-3] + w[:, 2:3] * m[3:-1] + w[:, 3:4] * m[4:]
    d[2:-2] = m[2:-2] - pred
    gain[2:-2] = 1.0 + np.sum(w * w, axis=1)
    # the two samples at each end: linear extrapolation from the next two inside
    d[0] = m[0] - (2 * m[1] - m[2])
    d[1] = m[1] - 0.5 * (m[0] + m[2])
    d[-2] = m[-2] - 0.5 * (m[-1] + m[-3])
    d[-1] = m[-1] - (2 * m[-2] - m[-3])
    gain[[0, -1]] = 6.0
    gain[[1, -2]] = 1.5
    return d / np.sqrt(gain)[:, None], gain


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
        blk = trimmed_scale(d[: nb * _LOCAL].reshape(nb, _LOCAL, d.shape[1]), axis=1)
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


def _culprit(i: int, m: np.ndarray, g: np.ndarray, candidate: np.ndarray, worst) -> int:
    """Peak ``i`` or, if repairing it (replaced by interpolation from its neighbours) leaves
    a score over the threshold around it, the candidate within ±2 (over the threshold and
    isolated) whose repair leaves none: a glitch disturbs its neighbours' predictions too, and
    next to a gap in the timestamps a neighbour's disturbance can outscore the glitch's own
    innovation."""
    n = len(m)
    lo, hi = max(i - 7, 0), min(i + 8, n)

    def left_over(j: int) -> float:
        mw = m[lo:hi].copy()
        gw = g[lo:hi]
        k = j - lo
        others = np.flatnonzero(np.arange(hi - lo) != k)
        for a in range(3):
            mw[k, a] = np.interp(gw[k], gw[others], mw[others, a])
        sc = worst(mw, gw, lo)
        sc[k] = 0.0
        return float(np.max(sc[max(i - 3 - lo, 0) : i + 4 - lo]))

    if left_over(i) <= 1.0:
        return i
    for j in sorted((j for j in range(max(i - 2, 0), min(i + 3, n)) if j != i and candidate[j]), key=lambda j: abs(j - i)):
        if left_over(j) <= 1.0:
            return j
    return i


def _radial(m: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Centre and radius of a quick sphere fit for the radial channel, or None when the samples
    describe no sphere (a still board). Thin coverage is accepted: only the smoothness of
    |m − c| − r matters here, not the centre's accuracy."""
    start = sphere_start(m, max_condition=np.inf) if len(m) >= 10 else None
    if start is None or isinstance(start, FitFailure):
        return None
    return start[:3], float(start[3])


def _side_ok(m: np.ndarray, g: np.ndarray, floor: np.ndarray, thr: float) -> np.ndarray:
    """Off the linear trend from the left AND from the right, and to the same side of both (a
    step or a fast swing agrees with one side, a transition leaves one trend upwards and meets
    the other from below; a glitch jumps and comes back). Where a gap in the timestamps lies
    inside either trend's pair of samples, the direction of that trend says little and only
    the distance is asked for."""
    left, right = _one_sided(m)
    same_way = np.sum(left * right, axis=1) > 0
    step = np.diff(g)
    gap = np.zeros(len(m), bool)
    gap[2:] |= step[:-1] > 1.5  # between i−2 and i−1
    gap[:-2] |= step[1:] > 1.5  # between i+1 and i+2
    return (np.minimum(_z(left, floor), _z(right, floor)) > thr) & (same_way | gap)


def detect(m: np.ndarray, t: np.ndarray, alpha: float = 0.01, max_rounds: int = 8) -> Glitches:
    m = np.array(m, dtype=np.float64, copy=True)
    n = len(m)
    g = sample_grid(np.asarray(t, np.float64))
    floor = 0.5 * _quantum(m) if n > 3 else np.full(3, 1e-3)
    w = _weights(g) if n >= 5 else None  # the prediction weights of the whole series, for each of its innovations
    d, gain = innovations(m, g, w)
    noise = float(np.median(trimmed_scale(d))) if n else 0.0
    sphere = _radial(m) if n >= 10 else None
    channels = 2 if sphere is not None else 1
    thr = float(np.sqrt(chi2_isf(alpha / (channels * max(n, 1)), 3))) if n else np.inf
    thr_r = float(np.sqrt(chi2_isf(alpha / (2 * max(n, 1)), 1))) if sphere is not None else np.inf
    side_thr = float(np.sqrt(chi2_isf(alpha, 3)))
    side_thr_r = float(np.sqrt(chi2_isf(alpha, 1)))
    floor_r = np.array([float(np.min(floor))])

    def radial_series(mm):
        return (np.linalg.norm(mm - sphere[0], axis=1) - sphere[1])[:, None]

    flagged = np.zeros(n, bool)
    by_radial = np.zeros(n, bool)
    zs = np.zeros(n)
    jumps = np.zeros(n)
    for _ in range(max_rounds):
        s3 = local_scale(d, floor)
        z = np.sqrt(np.sum((d / s3) ** 2, axis=1))
        z[flagged] = 0
        score = z / thr
        if sphere is not None:
            r = radial_series(m)
            dr, _ = innovations(r, g, w)
            sr = local_scale(dr, floor_r)
            zr = np.abs(dr[:, 0]) / sr[:, 0]
            zr[flagged] = 0
            score = np.maximum(score, zr / thr_r)
        ok3 = z > thr  # the side check (two local scales of its own) only when some sample is over it
        ok3 = ok3 & _side_ok(m, g, floor, side_thr) if ok3.any() else ok3
        okr = np.zeros(n, bool)
        if sphere is not None:
            okr = zr > thr_r
            okr = okr & _side_ok(r, g, floor_r, side_thr_r) if okr.any() else okr
        # candidates: over the threshold and isolated in the channel that flags them; of
        # those, the largest within ±2 samples (a glitch also disturbs its neighbours'
        # predictions, and a gap in the timestamps can make a neighbour's larger still)
        cand = np.where(ok3 | okr, score, 0.0)
        if not cand.any():
            break
        zp = np.pad(cand, 2)
        peak = cand > 0
        for s in (1, 2):
            peak &= cand >= zp[2 - s : 2 - s + n]
            peak &= cand >= zp[2 + s : 2 + s + n]

        def worst(mw, gw, lo):
            """Each sample's larger channel score (over its threshold) in a repaired window."""
            dw, _ = innovations(mw, gw)
            sc = np.sqrt(np.sum((dw / s3[lo : lo + len(mw)]) ** 2, axis=1)) / thr
            if sphere is not None:
                drw, _ = innovations(radial_series(mw), gw)
                sc = np.maximum(sc, np.abs(drw[:, 0]) / sr[lo : lo + len(mw), 0] / thr_r)
            return sc

        idx = np.unique([_culprit(int(i), m, g, cand > 0, worst) for i in np.flatnonzero(peak)]).astype(np.int64)
        flagged[idx] = True
        by_radial[idx] = okr[idx] & ~ok3[idx]
        zs[idx] = z[idx]
        jumps[idx] = np.linalg.norm(d[idx], axis=1) * np.sqrt(gain[idx])
        good = np.flatnonzero(~flagged)
        if len(good) < 3:
            break
        for a in range(3):  # repair by interpolation from unflagged samples
            m[idx, a] = np.interp(g[idx], g[good], m[good, a])
        d, gain = innovations(m, g, w)
    # bursts (three or more flags within five samples) are fast motion, not glitches
    if flagged.any():
        c = np.convolve(flagged.astype(int), np.ones(5, int), mode="same")
        burst = np.convolve((c >= 3).astype(int), np.ones(5, int), mode="same") > 0
        flagged &= ~burst
    idx = np.flatnonzero(flagged)
    return Glitches(idx, zs[idx], jumps[idx], thr, noise, thr_r, by_radial[idx])


def describe(glitch: Glitches, rows: np.ndarray, times: np.ndarray, radial_ut: np.ndarray) -> Finding:
    """The ``outliers`` finding: ``rows`` and ``times`` of the flagged samples (file rows and
    seconds), ``radial_ut`` how far each lies off the baseline sphere."""
    seen = float(np.median(np.abs(radial_ut) / np.maximum(glitch.jump_ut, 1e-9)))
    summary = (
        f"{len(glitch.index)} sample(s) jump off the smooth trajectory by {np.median(glitch.jump_ut):.1f} µT "
        f"(median) and straight back: isolated read glitches or corrupted samples, not field. "
        + (
            f"Only about {100 * seen:.0f} % of a jump shows in |m|, so a radius check alone misses the sideways ones."
            if seen < 0.7
            else f"About {100 * min(seen, 1.0):.0f} % of a jump shows in |m|: these jumps are mostly radial."
        )
    )
    return Finding(
        effect="outliers",
        summary=summary,
        where={"time_s": [float(v) for v in times[:200]], "n": int(len(glitch.index))},
        evidence={
            "test": "neighbour-interpolation innovation of the 3-vector (chi2(3)) and of |m - c| - r (chi2(1)), "
            "robust local scales, Bonferroni over samples and both channels",
            "threshold_z": glitch.threshold_z,
            "threshold_radial_z": glitch.threshold_radial_z if np.isfinite(glitch.threshold_radial_z) else None,
            "n_seen_in_magnitude_only": int(np.sum(glitch.radial)),
            "z": [float(v) for v in glitch.z[:200]],
            "jump_ut": [float(v) for v in glitch.jump_ut[:200]],
            "median_radial_change_ut": float(np.median(np.abs(radial_ut))),
            "median_radial_share_of_jump": seen,
        },
        params={"indices": [int(v) for v in rows]},
    )
