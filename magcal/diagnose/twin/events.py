"""Intermittent disturbances of the field's magnitude in a radial residual: the stretches, the
wander's level beneath each, and the (size, duration) pairs the twin draws back.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from ...sim import wander as wander_mod
from ...sim.disturbance import Disturbances


EVENT_Z = 4.5  # a disturbance departs from the median radius by this many robust σ at its peak
EVENT_EDGE = 2.0  # and lasts while it stays beyond this many
EVENT_MIN = 1  # and more than twice what a Gaussian residual would make
MAX_EVENTS = 64  # disturbance (size, duration) pairs kept in a model


def disturbances(e: np.ndarray, t: np.ndarray) -> tuple[Disturbances | None, np.ndarray, np.ndarray]:
    """(the disturbance process, the samples it covers, the residual with each of them
    replaced by the wander's level there, ``_beneath``) of a radial residual: stretches whose
    peak departs from the median by more than EVENT_Z robust σ, each extended while it stays
    beyond EVENT_EDGE σ. None unless there are at least EVENT_MIN and more than twice what a
    Gaussian residual of that σ would make (at 4.5σ, one in 150 000 samples); one event is
    enough to estimate a rate (1 per recording), and the twins then differ in how many they
    draw, as recordings of the same sensor would. Sizes and durations: ``event_pairs`` of the
    departures from the wander beneath them, lengths in samples × the sample period."""
    n = len(e)
    hit = np.zeros(n, bool)
    if n < 50:
        return None, hit, e
    a = e - np.median(e)
    sigma = max(1.4826 * float(np.median(np.abs(a))), 1e-12)
    edge = np.abs(a) > EVENT_EDGE * sigma
    d = np.diff(np.concatenate([[0], edge.astype(np.int8), [0]]))
    lo, hi = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    peaks = np.array([a[i:j][np.argmax(np.abs(a[i:j]))] for i, j in zip(lo, hi)]) if len(lo) else np.zeros(0)
    big = np.abs(peaks) > EVENT_Z * sigma
    expected = n * 2 * float(ndtr(-EVENT_Z))
    if big.sum() < max(EVENT_MIN, 2 * expected):
        return None, hit, e
    lo, hi, peaks = lo[big], hi[big], peaks[big]
    wander = np.array(a, dtype=np.float64)
    dep = []
    for i, j, v in zip(lo, hi, _beneath(a, lo, hi)):
        hit[i:j] = True
        dep.append(a[i:j] - v)
        wander[i:j] = v
    dt = wander_mod.sample_interval(t)  # samples to seconds at the rate the twin draws them back
    span = max(float(t[-1] - t[0]) + dt, dt)
    pairs = event_pairs(dep, dt)
    return Disturbances(rate_per_s=len(peaks) / span, size_ut=(float(pairs[:, 0].min()), float(pairs[:, 0].max())),
                        duration_s=(float(pairs[:, 1].min()), float(pairs[:, 1].max())),
                        up_share=float(np.mean(peaks > 0)), events=tuple(map(tuple, pairs))), hit, wander + np.median(e)


def _beneath(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list:
    """Per stretch a[lo:hi], the wander's level beneath it: the straight line from the median
    of the stretch's length of samples before it to the median of as many after it (samples
    of other stretches left out; one side alone when the other has none, 0 when neither)."""
    out = np.ones(len(a), bool)
    for i, j in zip(lo, hi):
        out[i:j] = False
    levels = []
    for i, j in zip(lo, hi):
        k = j - i
        before, after = a[max(i - k, 0):i][out[max(i - k, 0):i]], a[j:j + k][out[j:j + k]]
        left = float(np.median(before)) if len(before) else None
        right = float(np.median(after)) if len(after) else None
        left, right = (left if left is not None else right), (right if right is not None else left)
        levels.append(np.linspace(left or 0.0, right or 0.0, k))
    return levels


def event_pairs(dep: list, dt_s: float) -> np.ndarray:
    """(k, 2): size µT and duration s of the disturbances whose departures from the wander
    beneath them are ``dep`` (samples ``dt_s`` apart). Each is read as the hold of equal
    energy — its RMS departure for its length — so that the process gives back the power the
    stretches take out of the residual the wander is fitted to: a stretch is a bump that rises
    through the edge to its peak and falls back, and a hold at its peak for its whole length
    carried 4.4× its energy on hmc5843 ucalgary. Kept as pairs (the twin draws one pair per
    event): sizes and durations drawn apart, each log-uniform over its 5–95 % range, lost how
    they go together and the few longest holds, which carry most of the power. At most
    MAX_EVENTS, at evenly spaced ranks of energy."""
    pairs = np.array([(max(np.sqrt(np.mean(x**2)), 1e-12), len(x) * dt_s) for x in dep])
    if len(pairs) > MAX_EVENTS:
        order = np.argsort(pairs[:, 0] ** 2 * pairs[:, 1], kind="stable")
        pairs = pairs[order[np.round(np.linspace(0, len(pairs) - 1, MAX_EVENTS)).astype(np.int64)]]
    return pairs
