"""How much a recording says that a stretch of it was read through an axis transform (two axes
exchanged, one negated), judged by the total evidence rather than by a count of samples.

Two independent views, each a log-likelihood ratio (nats) of "this stretch was read through the
transform" against "as read", over the fresh readings (an exact repeat of the reading before it is
the same conversion read again and says nothing new):

- **radial**: the radial residual against the surface the rest of the data describes, as read and
  transformed, modelled as a first-order autoregression (a misfit that drifts slowly is not
  evidence: only what its innovations cannot explain is) whose innovations are Gaussian at the
  scatter measured on the recording, mixed with outliers at the share and reach seen there. A stretch is claimed on it when the total beats ``log(transforms · n² / ALPHA)``
  (every stretch of every transform tried).
- **edges**: the trajectory. A transform is an isometry, so inside a transformed stretch the
  steps from sample to sample are the same as read; only its two ends differ. A swap makes the
  reading jump at each end, and read back through the transform those jumps are ordinary steps.
  Each step is modelled as Gaussian in 3-D at the local typical step (the running median of
  ``STEP_WINDOW`` steps), widened on an axis whose own steps run larger there (a line on that
  axis: a 50 Hz hum steps one axis by several µT every reading), mixed with jumps at the share seen on the recording, spread over a
  ball twice the field across. A stretch is claimed on it when each end alone beats
  ``log(transforms · n / ALPHA)``. This sees a swap the radius cannot (x and y offsets equal: the
  swap maps the surface onto itself).

Either view needs at least two fresh readings inside: one reading cannot tell a transform from a
glitch that happens to land on the transformed surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy import ndimage

from ...fit.outliers import robust_sigma

OUTLIER_K = 5.0  # an innovation or step beyond this × its scale counts towards the outlier share
ALPHA = 0.01  # the chance, over every stretch tried, of claiming one on a recording without
STEP_WINDOW = 21  # steps in the running median that sets the local typical step
CHI3_MEDIAN = 1.5382  # median length of a standard Gaussian vector in 3-D
HALF_NORMAL_MEDIAN = 0.6745  # median of |x| for a standard Gaussian x
MIN_FRESH = 2
MAX_STRETCHES = 8  # per transform and view
TAKEN = -1e12  # the evidence written over a stretch already taken: no later one crosses it


class View(Enum):
    """Which evidence found a stretch."""

    RADIAL = "radial"
    EDGES = "edges"


@dataclass(frozen=True)
class Stretch:
    """Fresh readings ``first``…``last`` read through transform ``transform``; ``evidence`` and
    ``threshold`` in nats; ``view`` which evidence found it; ``jumps`` the two end steps as read and
    ``typical_step`` the local step there (µT, edges view)."""

    first: int
    last: int
    transform: int
    evidence: float
    threshold: float
    view: View
    jumps: tuple[float, float] = (float("nan"), float("nan"))
    typical_step: float = float("nan")


def _mixture(x: np.ndarray, scale, eps: float, spread: float) -> np.ndarray:
    """log density of ``x`` (1-D): Gaussian at ``scale`` with probability 1-eps, else uniform
    over [−``spread``, ``spread``]."""
    gauss = np.log1p(-eps) - 0.5 * (x / scale) ** 2 - np.log(scale * np.sqrt(2.0 * np.pi))
    return np.logaddexp(gauss, np.log(eps / (2.0 * spread)))


def _axis_scales(steps: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(n−1, 3) scale of each axis's step: the 3-D typical ``s``, widened on an axis whose own
    running median step is larger (a line on that axis, or the motion moving it fastest), so
    that axis's ordinary steps are not taken for jumps; never narrowed below ``s``."""
    own = ndimage.median_filter(np.abs(steps), size=(STEP_WINDOW, 1), mode="nearest") / HALF_NORMAL_MEDIAN
    return np.maximum(own, s[:, None])


def _mixture_3d(x: np.ndarray, scale: np.ndarray, eps: float, spread: float) -> np.ndarray:
    """log density of steps ``x`` (n, 3): Gaussian with per-axis ``scale`` (n, 3) with probability
    1-eps, else uniform over a ball of radius ``spread``."""
    gauss = np.log1p(-eps) - np.sum(0.5 * (x / scale) ** 2 + np.log(scale * np.sqrt(2.0 * np.pi)), axis=1)
    return np.logaddexp(gauss, np.log(eps / (4.0 / 3.0 * np.pi * spread ** 3)))


def _best(start: np.ndarray, inner: np.ndarray, stop: np.ndarray) -> tuple[float, int, int]:
    """max over a ≤ l of start[a] + Σ inner[a+1 … l] + stop[l], with its (a, l)."""
    s = np.r_[0.0, np.cumsum(inner)]
    vals = start - s[1:]
    acc = np.maximum.accumulate(vals)
    arg = np.maximum.accumulate(np.where(vals == acc, np.arange(len(vals)), 0))
    tot = acc + s[1:] + stop
    last = int(np.argmax(tot))
    return float(tot[last]), int(arg[last]), last


def _ar1(r0: np.ndarray, sigma: float) -> tuple[float, float, float, float]:
    """(lag-one coefficient, innovation scale, outlier share, outlier spread) of the as-read
    radial residual. Outliers are spread as far as the recording's own reach: uniform out to
    twice their median size (a glitch of a few µT is no evidence that a reading belongs on a
    surface it misses by less)."""
    c = np.clip(r0, -OUTLIER_K * sigma, OUTLIER_K * sigma)
    c = c - c.mean()
    rho = float(np.clip(np.dot(c[1:], c[:-1]) / max(np.dot(c, c), 1e-300), 0.0, 0.999))
    e = r0[1:] - rho * r0[:-1]
    scale = robust_sigma(e)
    scale = scale if scale > 0 else sigma
    out = np.abs(e[np.abs(e) > OUTLIER_K * scale])
    spread = 2.0 * float(np.median(out)) if len(out) else 2.0 * OUTLIER_K * scale
    return rho, scale, max(1.0 / len(r0), len(out) / len(e)), spread


def radial(r: np.ndarray, sigma: float) -> list[Stretch]:
    """Stretches the radial residual ``r`` (row 0 as read, row j+1 through transform j; fresh
    readings in order) says were transformed."""
    r0, n = r[0], r.shape[1]
    rho, scale, eps, spread = _ar1(r0, sigma)
    ll = lambda e: _mixture(e, scale, eps, spread)  # noqa: E731
    l0 = np.r_[ll(r0[:1]), ll(r0[1:] - rho * r0[:-1])]
    thr = float(np.log((r.shape[0] - 1) * n * n / ALPHA))
    out = []
    for j in range(r.shape[0] - 1):
        rt = r[j + 1]
        start = np.r_[ll(rt[:1]), ll(rt[1:] - rho * r0[:-1])] - l0
        inner = np.r_[0.0, ll(rt[1:] - rho * rt[:-1]) - l0[1:]]
        stop = np.r_[ll(r0[1:] - rho * rt[:-1]) - l0[1:], 0.0]
        out += [Stretch(a, b, j, e, thr, View.RADIAL) for e, a, b in _scan(start, inner, stop, thr)]
    return out


def _scan(start, inner, stop, thr) -> list[tuple[float, int, int]]:
    """The best stretches, one at a time, each taken out before the next is sought."""
    start, inner, stop = start.copy(), inner.copy(), stop.copy()
    out = []
    for _ in range(MAX_STRETCHES):
        e, a, b = _best(start, inner, stop)
        if e < thr:
            break
        if b - a + 1 >= MIN_FRESH:
            out.append((e, a, b))
        start[a : b + 1] = inner[a : b + 1] = stop[a : b + 1] = TAKEN
    return out


def edges(m: np.ndarray, transforms, field_ut: float) -> list[Stretch]:
    """Stretches of the fresh readings ``m`` (n, 3) whose two ends jump as read and are ordinary
    steps read through one of ``transforms`` ((permutation, signs) pairs)."""
    n = len(m)
    if n < STEP_WINDOW:
        return []
    steps = np.diff(m, axis=0)
    d = np.linalg.norm(steps, axis=1)
    s = ndimage.median_filter(d, size=STEP_WINDOW, mode="nearest") / CHI3_MEDIAN
    s = np.maximum(s, 1e-9 * max(field_ut, 1e-9))
    axis_s = _axis_scales(steps, s)
    eps = max(1.0 / n, float(np.mean(np.any(np.abs(steps) > OUTLIER_K * axis_s, axis=1))))
    ll = lambda x: _mixture_3d(x, axis_s, eps, 2.0 * field_ut)  # noqa: E731
    l0 = ll(steps)
    thr = float(np.log(len(transforms) * n / ALPHA))
    out = []
    for j, (perm, signs) in enumerate(transforms):
        mt = m[:, perm] * np.asarray(signs, float)
        enter = np.r_[-np.inf, ll(mt[1:] - m[:-1]) - l0]  # reading i the first transformed
        leave = np.r_[ll(m[1:] - mt[:-1]) - l0, -np.inf]  # reading i the last
        for a, b in _pairs(np.flatnonzero(enter >= thr), np.flatnonzero(leave >= thr)):
            out.append(Stretch(a, b, j, float(enter[a] + leave[b]), 2.0 * thr, View.EDGES,
                               (float(d[a - 1]), float(d[b])), float(np.median(s[[a - 1, b]]) * CHI3_MEDIAN)))
    return out


def _pairs(enter: np.ndarray, leave: np.ndarray) -> list[tuple[int, int]]:
    """Each entry with the first exit at least ``MIN_FRESH`` - 1 readings later, with no other
    entry before that exit."""
    out = []
    for k, a in enumerate(enter):
        later = leave[leave >= a + MIN_FRESH - 1]
        if not len(later):
            continue
        b = int(later[0])
        if k + 1 < len(enter) and enter[k + 1] <= b:
            continue
        out.append((int(a), b))
    return out


__all__ = ["ALPHA", "Stretch", "View", "edges", "radial"]
