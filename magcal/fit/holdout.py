"""Which model predicts the rest of the recording? Time-blocked held-out judgement.

A model's in-sample fit says little about the next recording: a full ellipsoid always fits a
recording at least as well as a sphere, and the information criteria (BIC) assume independent
residuals, which real recordings do not have (the board lingers, the offset wanders). What a
user sees is how the calibration does on samples it was not fitted to, later in time.

``judge`` cuts the samples into ``N_BLOCKS`` contiguous time blocks. For each block, each
candidate model is refitted on the other blocks (plain least squares from its whole-recording
solution) and judged on the block by the spread of |calibrated field| (std/mean, what a
held-out check measures); a model's score is the root mean square of its blocks' spreads,
weighted by the samples judged.

Two sets of samples are judged. The model is chosen on the samples of each block whose
direction cell the other blocks also visit: a block whose directions the rest never saw
judges extrapolation, which on a short recording is a handful of samples deciding against the
model the rest determines well (such blocks, under ``SEEN_SHARE`` of their samples seen, are
named in ``HeldOut.unseen_blocks`` so the reason can say so). The direction balance is judged
on all of them, since the directions a recording holds least are what it is for: an
ellipsoid is refitted with it and without, and the balance is dropped only where the plain
fit predicts ``BALANCE_MARGIN`` times better.

The blocks are few and short, so their figures carry noise of several per cent: a model the
in-sample criterion (``fit``'s BIC) prefers is replaced only by one that predicts its blocks
better by more than ``MARGIN`` — never kept where the sphere, or any other determined model,
is that much better on them.
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
MARGIN = 0.05
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

    def choose(self, default: str, margin: float = MARGIN) -> str:
        """``default`` unless another kind predicts the held-out blocks better by more than
        ``margin`` (relative); then the best of those (a tie goes to the simpler model)."""
        better = [k for k in SIMPLER_FIRST if k in self.spread and self.spread[k] * (1 + margin) < self.spread[default]]
        return min(better, key=lambda k: (self.spread[k], SIMPLER_FIRST.index(k))) if better else default


def block_edges(n: int, n_blocks: int = N_BLOCKS) -> np.ndarray:
    return np.linspace(0, n, n_blocks + 1).astype(np.int64)


def spread(m: np.ndarray, theta: np.ndarray, kind: str) -> float:
    """std/mean of |W(m − b)| over the samples."""
    b, _, W = geometric.unpack(theta, kind)
    h = np.linalg.norm((m - b) @ W.T, axis=1)
    return float(np.std(h) / np.mean(h))


def _refit(m_train: np.ndarray, g: geometric.GeometricFit, balanced: bool):
    """The model refitted on a training part, from its whole-recording solution."""
    weights = None
    if balanced:
        weights = direction_weights((m_train - g.offset_ut) @ g.soft_iron.T)
    return geometric.solve(m_train, g.kind, g.theta, weights=weights)


def _rms(parts: list) -> float:
    n = sum(k for k, _ in parts)
    return float(np.sqrt(sum(k * v**2 for k, v in parts) / n)) if n else float("inf")


def _score(m, g, keep, tests: dict, edges, balanced: bool) -> dict:
    """{name: RMS over blocks (weighted by judged samples) of one model's held-out spread} for
    each set of judged samples in ``tests`` ({name: per-block masks}); one refit per block."""
    parts: dict = {name: [] for name in tests}
    for j in range(len(edges) - 1):
        inside = np.zeros(len(m), bool)
        inside[edges[j] : edges[j + 1]] = True
        f = _refit(m[keep & ~inside], g, balanced)
        if isinstance(f, FitFailure):
            return {name: float("inf") for name in tests}
        for name, masks in tests.items():
            if masks[j].sum() >= MIN_BLOCK:
                parts[name].append((int(masks[j].sum()), spread(m[masks[j]], f.theta, g.kind)))
    return {name: _rms(p) for name, p in parts.items()}


def _tests(m, judged, edges, offset_ut) -> tuple[dict, list]:
    """Per block, the samples it judges — "all" kept by every model, "seen" those of them in a
    direction cell the other blocks also visit — and the blocks that mostly lie elsewhere."""
    cells = cell_index(m - offset_ut)
    tests: dict = {"all": [], "seen": []}
    unseen = []
    for j in range(len(edges) - 1):
        inside = np.zeros(len(m), bool)
        inside[edges[j] : edges[j + 1]] = True
        seen = np.isin(cells, np.unique(cells[~inside]))
        if np.mean(seen[inside]) < SEEN_SHARE:
            unseen.append(j)
        tests["all"].append(judged & inside)
        tests["seen"].append(judged & inside & seen)
    return tests, unseen


def judge(m: np.ndarray, candidates: dict, n_blocks: int = N_BLOCKS) -> HeldOut | None:
    """Held-out spreads of each candidate ({kind: (GeometricFit, kept mask)}) on ``m`` (the
    samples in time order), or None where the recording is too short to cut into blocks."""
    judged = np.logical_and.reduce([keep for _, keep in candidates.values()])
    edges = block_edges(len(m), n_blocks)
    if np.min(np.add.reduceat(judged, edges[:-1])) < MIN_BLOCK:
        return None
    sphere = candidates.get("sphere", next(iter(candidates.values())))[0]
    tests, unseen = _tests(m, judged, edges, sphere.offset_ut)
    scores, balanced = {}, {}
    for k, (g, keep) in candidates.items():
        plain = _score(m, g, keep, tests, edges, False)
        weighted = plain if k == "sphere" else _score(m, g, keep, tests, edges, True)
        balanced[k] = k != "sphere" and weighted["all"] <= BALANCE_MARGIN * plain["all"]
        scores[k] = (weighted if balanced[k] else plain)["seen"]
    if not np.isfinite(min(scores.values())):
        return None
    return HeldOut(scores, n_blocks, tuple(unseen), balanced)
