"""Which model predicts the rest of the recording? Time-blocked held-out judgement.

A model's in-sample fit says little about the next recording: a full ellipsoid always fits a
recording at least as well as a sphere, and the information criteria (BIC) assume independent
residuals, which real recordings do not have (the board lingers, the offset wanders). What a
user sees is how the calibration does on samples it was not fitted to, later in time.

``judge`` cuts the samples into ``N_BLOCKS`` contiguous time blocks. For each block, each
candidate model is refitted on the other blocks (plain least squares from its whole-recording
solution; an ellipsoid with the direction balance, and without it, which is kept only where it
predicts ``BALANCE_MARGIN`` times better: time blocks mostly judge directions the rest also
holds, while the balance is for the ones it holds least) and judged on the block by
the spread of |calibrated field| (std/mean, what a held-out check measures). A model's score is
the root mean square of its blocks' spreads, weighted by block size.

A block whose directions the other blocks hardly show (less than ``SEEN_SHARE`` of its samples
in a direction cell the rest also visits) judges extrapolation, not prediction. Such blocks
are kept in the score — how a model extrapolates is what the next recording tests — and named
(``HeldOut.unseen_blocks``) so the reason can say so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometric
from .coverage import cell_index
from .direction_weights import direction_weights
from .failure import FitFailure

N_BLOCKS = 5
MIN_BLOCK = 30
SEEN_SHARE = 0.5
BALANCE_MARGIN = 1.25
SIMPLER_FIRST = ("sphere", "diagonal", "full")


@dataclass(frozen=True)
class HeldOut:
    """Per model kind, its held-out spread (fraction, RMS over blocks; inf where a refit failed)
    and whether the direction balance gave it (``balanced``), the blocks judged (count) and
    those that judged extrapolation (0-based)."""

    spread: dict
    n_blocks: int
    unseen_blocks: tuple[int, ...]
    balanced: dict

    def best(self) -> str:
        """The kind with the lowest held-out spread; a tie goes to the simpler model."""
        kinds = [k for k in SIMPLER_FIRST if k in self.spread]
        return min(kinds, key=lambda k: (self.spread[k], SIMPLER_FIRST.index(k)))


def block_edges(n: int, n_blocks: int = N_BLOCKS) -> np.ndarray:
    return np.linspace(0, n, n_blocks + 1).astype(np.int64)


def spread(m: np.ndarray, theta: np.ndarray, kind: str) -> float:
    """std/mean of |W(m − b)| over the samples."""
    b, _, W = geometric.unpack(theta, kind)
    h = np.linalg.norm((m - b) @ W.T, axis=1)
    return float(np.std(h) / np.mean(h))


def seen_share(cells: np.ndarray, test: np.ndarray, train: np.ndarray) -> float:
    """Share of the test samples whose direction cell the training samples also visit."""
    return float(np.mean(np.isin(cells[test], np.unique(cells[train]))))


def _refit(m_train: np.ndarray, g: geometric.GeometricFit, balanced: bool):
    """The model refitted on a training part, from its whole-recording solution."""
    weights = None
    if balanced:
        weights = direction_weights((m_train - g.offset_ut) @ g.soft_iron.T)
    return geometric.solve(m_train, g.kind, g.theta, weights=weights)


def _score(m, g, keep, judged, edges, balanced: bool) -> float:
    """RMS over blocks (weighted by judged samples) of the held-out spread of one model."""
    total, weight = 0.0, 0
    for j in range(len(edges) - 1):
        inside = np.zeros(len(m), bool)
        inside[edges[j] : edges[j + 1]] = True
        f = _refit(m[keep & ~inside], g, balanced)
        if isinstance(f, FitFailure):
            return float("inf")
        test = judged & inside
        total += test.sum() * spread(m[test], f.theta, g.kind) ** 2
        weight += test.sum()
    return float(np.sqrt(total / max(weight, 1)))


def judge(m: np.ndarray, candidates: dict, n_blocks: int = N_BLOCKS) -> HeldOut | None:
    """Held-out spreads of each candidate ({kind: (GeometricFit, kept mask)}) on ``m`` (the
    samples in time order), or None where the recording is too short to cut into blocks."""
    judged = np.logical_and.reduce([keep for _, keep in candidates.values()])
    edges = block_edges(len(m), n_blocks)
    if np.min(np.add.reduceat(judged, edges[:-1])) < MIN_BLOCK:
        return None
    sphere = candidates.get("sphere", next(iter(candidates.values())))[0]
    cells = cell_index(m - sphere.offset_ut)
    unseen = []
    for j in range(n_blocks):
        idx = np.arange(edges[j], edges[j + 1])
        rest = np.r_[0 : edges[j], edges[j + 1] : len(m)]
        if seen_share(cells, idx, rest) < SEEN_SHARE:
            unseen.append(j)
    scores, balanced = {}, {}
    for k, (g, keep) in candidates.items():
        plain = _score(m, g, keep, judged, edges, False)
        weighted = plain if k == "sphere" else _score(m, g, keep, judged, edges, True)
        balanced[k] = k != "sphere" and weighted <= BALANCE_MARGIN * plain
        scores[k] = weighted if balanced[k] else plain
    return HeldOut(scores, n_blocks, tuple(unseen), balanced)
