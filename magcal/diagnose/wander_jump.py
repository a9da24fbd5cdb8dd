"""One jump in the offset's wander: the block offsets change once, not slowly.

The offset wander (channels.block_wander: an offset fitted in each of 20 time blocks) is
usually spread through a recording — 1/f noise, the environment. When instead most of its
departure is one change between two stretches of blocks, something moved the offset at a time
(a part put down, a cable moved): that is structure located in time, even where the local step
search (magcal.diagnose.locate.steps) does not clear its threshold, and it is said as the honest
remainder with its time — not as a hard-iron step, which was not proven.

A jump is said when both hold:
- the best split of the blocks into a before and an after carries at least ``JUMP_SHARE`` of
  their squared departure from the overall mean (a slow wander's best split carries less: on
  104 real control windows the largest share was 0.80, and that one failed the next test);
- the jump adds to a slow wander (Legendre degrees up to wander.NUISANCE_DEGREE over the
  blocks' times) beyond chance: F(3, dof) at the diagnosis' α, Bonferroni over the splits
  tried, each block weighted by how firmly its directions pin its offset (its Gram matrix) and
  judged against the blocks' own scatter about that fit — the recording's roughness at the
  blocks' scale, not the within-block noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre

from ..fit.tails import f_sf
from .channels import WanderBlocks, _departures
from . import timewords
from .limits import Limit
from .locate.base import REST
from .wander import NUISANCE_DEGREE

JUMP_SHARE = 0.8
MIN_SIDE_BLOCKS = 2  # blocks on each side of a split


@dataclass(frozen=True)
class Jump:
    """The offset's change between the blocks before and after ``time_s`` (h frame, µT)."""

    time_s: float  # the boundary between the two stretches
    interval_s: tuple[float, float]  # the block before and the block after it: the jump lies in there
    jump_ut: np.ndarray
    share: float  # of the blocks' squared departure the split carries
    p_value: float  # of "no jump beyond a slow wander", over every split tried


def find_jump(w: WanderBlocks, t_s: np.ndarray, alpha: float) -> Jump | None:
    """The one jump that carries most of the wander ``w`` (module docstring), or None."""
    g, d = w.grams, w.offsets_ut
    splits = range(MIN_SIDE_BLOCKS, len(d) - MIN_SIDE_BLOCKS + 1)
    total = float(np.sum(w.departure_ut2))
    if len(splits) < 1 or total <= 0:
        return None
    shares = [1.0 - float(np.sum(_departures(g[:k], d[:k])) + np.sum(_departures(g[k:], d[k:]))) / total for k in splits]
    k = splits[int(np.argmax(shares))]
    share = max(shares)
    if share < JUMP_SHARE:
        return None
    p = min(1.0, _beyond_slow(w, t_s, k) * len(splits))
    if p >= alpha:
        return None
    t = np.asarray(t_s, float)
    before, after = w.blocks[k - 1], w.blocks[k]
    jump = _mean(g[k:], d[k:]) - _mean(g[:k], d[:k])
    return Jump(float(t[after.start]), (float(t[before.start]), float(t[after.stop - 1])), jump, share, p)


def _mean(g: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.linalg.solve(g.sum(axis=0), np.einsum("bij,bj->i", g, d))


def _beyond_slow(w: WanderBlocks, t_s: np.ndarray, k: int) -> float:
    """p of an F test: a jump after block ``k`` added to a slow wander of the block offsets."""
    t = np.asarray(t_s, float)
    mid = np.array([0.5 * (t[b.start] + t[b.stop - 1]) for b in w.blocks])
    span = float(mid[-1] - mid[0])
    tau = 2.0 * (mid - mid[0]) / span - 1.0 if span > 0 else np.zeros(len(mid))
    slow = legendre.legvander(tau, NUISANCE_DEGREE)  # (B, degree + 1)
    roots = [np.linalg.cholesky(x + 1e-12 * np.trace(x) * np.eye(3)).T for x in w.grams]
    y = np.concatenate([r @ o for r, o in zip(roots, w.offsets_ut)])
    base = np.vstack([r @ np.kron(v[None, :], np.eye(3)) for r, v in zip(roots, slow)])
    step = np.vstack([r * float(i >= k) for i, r in enumerate(roots)])
    rss0, rss1 = _rss(base, y), _rss(np.hstack([base, step]), y)
    dof = len(y) - base.shape[1] - 3
    if dof < 1 or rss1 <= 0:
        return 1.0
    return float(f_sf((rss0 - rss1) / 3.0 / (rss1 / dof), 3, dof))


def _rss(x: np.ndarray, y: np.ndarray) -> float:
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    e = y - x @ coef
    return float(e @ e)


def jump_limit(jump, floor_ut: float, located: tuple = ()) -> tuple[Limit, ...]:
    """The wander's one jump (``find_jump``), located in time but proven as no
    hard-iron step: the honest remainder, sized against the recording's own floor ``floor_ut``.
    Not said where something ``located`` (magcal.diagnose.locate) already sits in its interval."""
    if jump is None or any(_within(x.where.get("time_s", ()), jump.interval_s) for x in located):
        return ()
    size = float(np.linalg.norm(jump.jump_ut))
    over = size / floor_ut if floor_ut > 0 else float("inf")
    a, b = jump.interval_s
    p_text = "p < 1e-12" if jump.p_value < 1e-12 else f"p = {jump.p_value:.1g}"
    summary = (f"unexplained structure remains: {over:.1f}× the noise, at {timewords.instant(jump.time_s)} — most of the offset's "
               f"wander ({100 * jump.share:.0f} % of it) is one jump of {size:.2f} µT somewhere in {timewords.stretch(a, b)}, "
               f"not a slow wander ({p_text}); the step search proved no hard-iron step there, so none is claimed")
    details = {"jump_ut": [float(v) for v in jump.jump_ut], "size_ut": size, "size_over_floor": over,
               "share": jump.share, "p_value": jump.p_value, "time_interval_s": [a, b]}
    return (Limit(REST, True, summary, details=details, where={"time_s": [jump.time_s]}),)


def _within(times, interval: tuple[float, float]) -> bool:
    """Any instant or stretch of ``times`` touches ``interval``."""
    a, b = interval
    return any(lo <= b and hi >= a for lo, hi in (np.resize(np.asarray(x, float), 2) for x in times))
