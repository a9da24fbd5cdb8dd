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

A refit is Gauss–Newton from the whole-recording solution: its first step uses the residual
and Jacobian there, computed once for every block, weighting and model; it stops once a step
moves the parameters by less than ``STEP_SE`` of their standard error (the step's length in
the metric of the information matrix, in units of the residual's σ) — what remains is a small
fraction of that, far below anything a spread is reported to. Where a step does not lower the
cost, or the steps do not settle, ``geometric.solve`` (Levenberg–Marquardt) refits it instead.

Two sets of samples are judged. The model is chosen on the samples of each block whose
direction cell the other blocks also visit: a block whose directions the rest never saw
judges extrapolation, which on a short recording is a handful of samples deciding against the
model the rest determines well (such blocks, under ``SEEN_SHARE`` of their samples seen, are
named in ``HeldOutSpread.unseen_blocks`` so the reason can say so). The direction balance is judged
on all of them, since the directions a recording holds least are what it is for: an
ellipsoid is refitted with it and without, on the blocks both refits reach, and the balance is
dropped only where the plain fit predicts them ``BALANCE_MARGIN`` times better, or better on
every block beyond the scatter of its gain between blocks (a one-sided paired t-test at
``BALANCE_ALPHA``). The size of the blocks' gain foretells little: over the 46 open cells of
``bench/balance_foresight.py`` its rank correlation with the balance's forward effect is
+0.08, and dropping the balance wherever the plain fit predicts the blocks better, or better
per direction cell, lost more forward cells than it won. A gain that holds block by block is
another matter: the three open cells where the test fires (two flight logs) are three where
the balance lost forward by 3–15 %, and no cell of the static race against MotionCal has it
(largest t 1.7). Models are compared on the
blocks every one of them refitted (a refit that does not converge on one block is no verdict on
the others; the ArduPilot log's first compass, first 70 %, lost its plain ellipsoid to one).

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
from .tails import t_isf

N_BLOCKS = 5
MIN_BLOCK = 30
SEEN_SHARE = 0.5
BALANCE_MARGIN = 1.25
BALANCE_ALPHA = 0.05
MARGIN = 0.05
STEP_SE = 1e-3  # a refit stops once a step moves it less than this many standard errors
MAX_STEPS = 20


@dataclass(frozen=True)
class HeldOutSpread:
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
        better = [k for k in geometric.KINDS if k in self.spread and self.spread[k] * (1 + margin) < self.spread[default]]
        return min(better, key=lambda k: (self.spread[k], geometric.KINDS.index(k))) if better else default


def block_edges(n: int, n_blocks: int = N_BLOCKS) -> np.ndarray:
    return np.linspace(0, n, n_blocks + 1).astype(np.int64)


def spread(m: np.ndarray, theta: np.ndarray, kind: str, W: np.ndarray | None = None) -> float:
    """std/mean of |W(m − b)| over the samples; ``W``: geometric.unpack's, when already made."""
    W = geometric.expm_sym(geometric.shape_matrix(kind, theta[4:]))[0] if W is None else W
    h = geometric.row_norm((m - theta[:3]) @ W.T)  # np.linalg.norm's sums, in its order
    return float(np.std(h) / np.mean(h))


def _refit(m: np.ndarray, rows: np.ndarray, g: geometric.GeometricFit, balanced: bool, at_whole: tuple):
    """θ of ``g``'s model refitted on the samples ``m[rows]`` (a block's complement), from its
    whole-recording solution (``at_whole``: the residual and Jacobian there, every sample), or a
    FitFailure; see the module docstring."""
    m_train = m[rows]
    w = direction_weights((m_train - g.offset_ut) @ g.soft_iron.T) if balanced else None
    theta = _gauss_newton(m_train, g, w, at_whole[0][rows], at_whole[1][rows])
    if theta is not None:
        return theta
    f = geometric.solve(m_train, g.kind, g.theta, weights=w)
    return f if isinstance(f, FitFailure) else f.theta


def _gauss_newton(m: np.ndarray, g: geometric.GeometricFit, w, e: np.ndarray, jac: np.ndarray):
    """Gauss–Newton from ``g.theta`` (``e``, ``jac``: residual and Jacobian there) to a step
    under ``STEP_SE`` standard errors; None where a step raises the cost, the radius turns
    negative or ``MAX_STEPS`` do not settle."""
    theta, p = g.theta.copy(), len(g.theta)
    if len(m) <= p:
        return None
    for _ in range(MAX_STEPS):
        ew, jw = (e, jac) if w is None else (w * e, w[:, None] * jac)
        a, grad, cost = jac.T @ jw, jac.T @ ew, float(e @ ew)
        scale = np.sqrt(np.maximum(np.diag(a), 1e-300))
        try:
            step = -np.linalg.solve(a / np.outer(scale, scale), grad / scale) / scale
        except np.linalg.LinAlgError:
            return None
        theta = theta + step
        if not np.isfinite(theta).all() or theta[3] <= 0:
            return None
        if step @ a @ step <= STEP_SE**2 * cost / (len(m) - p):
            return theta
        e, jac = geometric.residual_jacobian(theta, m, g.kind)
        if not float(e @ (e if w is None else w * e)) <= cost:
            return None
    return None


def _rms(parts: list) -> float:
    n = sum(k for k, _ in parts)
    return float(np.sqrt(sum(k * v**2 for k, v in parts) / n)) if n else float("inf")


def _score(m, g, keep, tests: dict, edges, balanced: bool, at_whole: tuple) -> list:
    """Per block, {name: (samples judged, held-out spread)} of one model for each set of judged
    samples in ``tests`` ({name: per-block masks}; a set under ``MIN_BLOCK`` left out), or None
    where the refit without the block failed; one refit per block."""
    blocks: list = []
    for j in range(len(edges) - 1):
        rows = keep.copy()
        rows[edges[j] : edges[j + 1]] = False
        theta = _refit(m, rows, g, balanced, at_whole)
        if isinstance(theta, FitFailure):
            blocks.append(None)
            continue
        W = geometric.expm_sym(geometric.shape_matrix(g.kind, theta[4:]))[0]  # one W for every set judged
        blocks.append({name: (int(masks[j].sum()), spread(m[masks[j]], theta, g.kind, W))
                       for name, masks in tests.items() if masks[j].sum() >= MIN_BLOCK})
    return blocks


def _over(blocks: list, name: str, on: np.ndarray) -> float:
    """RMS (weighted by samples judged) of ``name``'s spreads over the blocks ``on``; inf
    where a block of them failed or none is left."""
    if any(b is None for b, use in zip(blocks, on) if use):
        return float("inf")
    return _rms([b[name] for b, use in zip(blocks, on) if use and name in b])


def _balance_kept(plain: list, weighted: list) -> bool:
    """Keep the direction balance unless the plain fit predicts the blocks both refitted,
    judged on all their samples, ``BALANCE_MARGIN`` times better, or better block by block
    beyond the blocks' own scatter (``_plain_better_throughout``); a refit that failed to
    converge on one block is no verdict on the other variant."""
    both = np.array([p is not None and w is not None for p, w in zip(plain, weighted)])
    if not both.any():
        return weighted.count(None) <= plain.count(None)
    if _plain_better_throughout(plain, weighted, both):
        return False
    return _over(weighted, "all", both) <= BALANCE_MARGIN * _over(plain, "all", both)


def _plain_better_throughout(plain: list, weighted: list, on: np.ndarray) -> bool:
    """Does the unweighted fit predict the blocks ``on`` better than the balanced one, block by
    block, beyond the scatter of that gain between blocks? A one-sided paired t-test at
    ``BALANCE_ALPHA`` on each block's log(balanced ÷ unweighted spread), all its samples (at
    least three blocks)."""
    r = np.array([np.log(max(w["all"][1], 1e-300) / max(p["all"][1], 1e-300))
                  for p, w, use in zip(plain, weighted, on) if use and "all" in p and "all" in w])
    if len(r) < 3:
        return False
    se = float(np.std(r, ddof=1)) / np.sqrt(len(r))
    if se == 0.0:
        return bool(np.mean(r) > 0.0)
    return float(np.mean(r)) / se > float(t_isf(BALANCE_ALPHA, len(r) - 1))


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


def judge(m: np.ndarray, candidates: dict, n_blocks: int = N_BLOCKS) -> HeldOutSpread | None:
    """Held-out spreads of each candidate ({kind: (GeometricFit, kept mask)}) on ``m`` (the
    samples in time order), or None where the recording is too short to cut into blocks."""
    judged = np.logical_and.reduce([keep for _, keep in candidates.values()])
    edges = block_edges(len(m), n_blocks)
    if np.min(np.add.reduceat(judged, edges[:-1])) < MIN_BLOCK:
        return None
    sphere = candidates.get("sphere", next(iter(candidates.values())))[0]
    tests, unseen = _tests(m, judged, edges, sphere.offset_ut)
    kept, balanced = {}, {}
    for k, (g, keep) in candidates.items():
        at_whole = _at_whole(m, g, keep)
        plain = _score(m, g, keep, tests, edges, False, at_whole)
        weighted = plain if k == "sphere" else _score(m, g, keep, tests, edges, True, at_whole)
        balanced[k] = k != "sphere" and _balance_kept(plain, weighted)
        kept[k] = weighted if balanced[k] else plain
    scores = {k: _over(b, "seen", _common(kept)) for k, b in kept.items()}
    if not np.isfinite(min(scores.values())):
        return None
    return HeldOutSpread(scores, n_blocks, tuple(unseen), balanced)


def _at_whole(m: np.ndarray, g: geometric.GeometricFit, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The residual and Jacobian of ``g`` at its θ on every sample of ``m``: its own, where it
    was fitted on every one of them (the same numbers, already made), else made here."""
    if keep.all():
        return g.residual_ut, g.jac
    return geometric.residual_jacobian(g.theta, m, g.kind)


def _common(kept: dict) -> np.ndarray:
    """The blocks every candidate refitted, or every block where none is (each model then
    scored inf where it failed): the models are compared on the same blocks."""
    ok = np.logical_and.reduce([[b is not None for b in blocks] for blocks in kept.values()])
    return ok if ok.any() else np.ones(len(ok), bool)
