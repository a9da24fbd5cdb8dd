"""Learning that a recording is made of takes (``magcal.sim.takes``): where its recorder paused
while the board was placed anew, and whether each placement sits at its own level.

A take starts where the field direction steps between two reads with the board still on both
sides: the step passes TAKE_MIN_DEG and is TAKE_RATIO times the largest of the STILL_READS
steps either side (a board turned by hand moves through its steps; a glitch steps out and back,
so its neighbour's step is as large). Such starts alone do not make takes that matter — a
recorder that pauses on a moving board (gearvr mag_data) shows some, and its level does not
jump there, and an offset that wanders moves the level at any turn of the board, by the turn's
share of it. The takes are learned only when the residual's level steps at the starts (the mean
of TAKE_WINDOW reads after less the mean of as many before) exceed what twins of the model
learned without takes make at the same starts: their mean square against the twins', χ² with
one degree per start, beyond TAKE_P.
"""

from __future__ import annotations

import numpy as np

from ...fit import tails
from ...sim.takes import Takes

TAKE_MIN_DEG = 2.0
TAKE_RATIO = 10.0
STILL_READS = 5
TAKE_WINDOW = 10
TAKE_P = 1e-3


def take_starts(u: np.ndarray) -> np.ndarray:
    """Indices of the reads that begin a new take, of unit directions ``u`` (n, 3)."""
    step = np.degrees(np.arccos(np.clip(np.sum(u[1:] * u[:-1], axis=1), -1.0, 1.0)))  # step j: u_j → u_j+1
    n, s = len(step), STILL_READS
    if n < 2 * s + 1:
        return np.zeros(0, np.int64)
    pad = np.concatenate([np.full(s, np.inf), step, np.full(s, np.inf)])
    windows = np.lib.stride_tricks.sliding_window_view(pad, s)  # windows[i] = pad[i:i + s]
    before, after = windows[:n], windows[s + 1:s + 1 + n]  # steps j−s … j−1 and j+1 … j+s
    still = np.maximum(before.max(axis=1), after.max(axis=1)) * TAKE_RATIO <= step
    return np.flatnonzero(still & (step >= TAKE_MIN_DEG)) + 1


def candidate(u: np.ndarray, t_s: np.ndarray) -> Takes | None:
    """The takes ``take_starts`` finds in directions ``u`` at times ``t_s`` (levels not yet
    read), or None when there are none with TAKE_WINDOW reads on both sides."""
    k = take_starts(u)
    k = k[(k >= TAKE_WINDOW) & (k <= len(u) - TAKE_WINDOW)]
    return Takes(start_s=tuple(np.unique(t_s[k]))) if len(k) else None


def level_steps(e: np.ndarray, t_s: np.ndarray, takes: Takes) -> np.ndarray:
    """At each take's start, the mean of ``e`` over the TAKE_WINDOW reads from it less the mean
    over as many before it."""
    w = TAKE_WINDOW
    k = np.searchsorted(t_s, np.asarray(takes.start_s))
    k = k[(k >= w) & (k <= len(e) - w)]
    c = np.concatenate([[0.0], np.cumsum(e)])
    return ((c[k + w] - c[k]) - (c[k] - c[k - w])) / w


def steps_exceed(real: np.ndarray, twins: list) -> bool:
    """Whether the level steps at the starts (``real``) exceed what the twins of a model
    without takes make there (``twins``: their steps at the same starts): the real mean square
    against the twins', χ² with one degree per start, beyond TAKE_P."""
    ref = float(np.mean([np.mean(x * x) for x in twins if len(x)])) if twins else 0.0
    if not len(real) or not ref > 0:
        return False
    return bool(tails.chi2_sf(float(real @ real) / ref, len(real)) < TAKE_P)


def with_levels(takes: Takes, e: np.ndarray, t_s: np.ndarray) -> Takes:
    """``takes`` with the spread of the levels of ``e`` between them."""
    return Takes(start_s=takes.start_s, level_sd_ut=float(np.std(takes.means(e, t_s))))
