"""How large a channel term must be before this recording reports it: the per-channel floors.

A term K·(x − x_ref) (µT per unit of channel x, along the direction k̂ = K/|K|) is reported when
it passes every gate of magcal.diagnose.selection. Each gate gives a smallest |K| along k̂:

* the test: its Wald statistic must reach the critical value of Holm's first step (α / m for m
  tests). With the test's covariance V of the coefficient (bias-corrected block-HAC, with the
  full model and the nuisances in place), a term of size a along k̂ has noncentrality
  a²·k̂ᵀV⁻¹k̂, so a = √(W_crit / k̂ᵀV⁻¹k̂) (× the test's twin inflation λ, inference.calibrated);
* the practical floor: the term's radial signature must reach max(0.03 µT, 0.1 × noise);
* the wander gate (slow channels and time): the term's block offsets must carry
  channels.WANDER_RATIO × the recording's own offset wander (channels.slow_term_floor_range).

A channel can be reported by the fast route (the rich-wander test at Holm's level, and the
quadratic-wander test at α) or the slow one (the quadratic-wander test at Holm's level, the
wander gate); its floor along k̂ is the smaller of the two, each
the largest of its gates. The floor is stated over 256 directions k̂: its median, and the best-
and worst-pinned ends (None when some direction is never pinned). At the floor a term's test
statistic sits at the critical value on average: a term of twice the floor is found with high
probability, one of half the floor rarely.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..fit.tails import f_isf
from .inference import WaldResult


@lru_cache(maxsize=1)
def directions() -> np.ndarray:
    """256 unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = 256
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def wald_floor(result: WaldResult | None, alpha_each: float) -> np.ndarray:
    """Per direction: the size at which the test's noncentrality reaches its critical value,
    raised by the test's calibration against the twin (λ, inference.calibrated) (inf where the
    test cannot see the direction, or when there was no test)."""
    dirs = directions()
    if result is None or result.cov is None or result.untestable:
        return np.full(len(dirs), np.inf)
    k, df2, nu = result.df1, float(result.df2), float(result.nu)
    w_crit = k * nu / df2 * float(f_isf(alpha_each, k, df2)) * max(result.inflation, 1.0)
    prec = np.linalg.pinv(result.cov, rcond=1e-10, hermitian=True)
    q = np.einsum("di,ij,dj->d", dirs, prec, dirs)
    with np.errstate(divide="ignore"):
        return np.where(q > 1e-12 * max(float(q.max()), 1e-300), np.sqrt(w_crit / np.maximum(q, 1e-300)), np.inf)


def practical_floor(x_centred: np.ndarray, offset_directions: np.ndarray, floor_ut: float) -> np.ndarray:
    """Per direction: the size at which the term's radial signature reaches ``floor_ut`` RMS."""
    dirs = directions()
    w = np.asarray(x_centred, np.float64)[:, None] * offset_directions
    m = w.T @ w / max(len(w), 1)
    q = np.einsum("di,ij,dj->d", dirs, m, dirs)
    with np.errstate(divide="ignore"):
        return np.where(q > 0, floor_ut / np.sqrt(np.maximum(q, 1e-300)), np.inf)


def gate_floor(block_energy: np.ndarray | None, wander_rms_ut: float, ratio: float) -> np.ndarray:
    """Per direction: the size at which the term's block offsets carry ``ratio`` × the wander
    (``block_energy`` is M of channels.slow_term_floor_range; None: not a slow channel)."""
    dirs = directions()
    if block_energy is None:
        return np.full(len(dirs), np.inf)
    q = np.einsum("di,ij,dj->d", dirs, block_energy, dirs)
    with np.errstate(divide="ignore"):
        return np.where(q > 1e-12, np.sqrt(ratio / np.maximum(q, 1e-300)) * wander_rms_ut, np.inf)


@dataclass(frozen=True)
class Floor:
    """A channel's floor over directions (µT per unit of the channel)."""

    typical: float  # median over directions (inf: never reported)
    lowest: float  # along the best-pinned direction
    highest: float  # along the worst-pinned direction (inf: some direction never pinned)
    route: str  # "fast" (rich-wander test) or "slow" (quadratic-wander test and wander gate)

    def to_dict(self) -> dict:
        def num(v):
            return float(v) if np.isfinite(v) else None

        return {"ut_per_unit": num(self.typical), "range_ut_per_unit": [num(self.lowest), num(self.highest)],
                "route": self.route}


def combine(fast: list[np.ndarray], slow: list[np.ndarray]) -> Floor:
    """The floor of a channel that passes by either route, each route by all of its gates."""
    f = np.max(np.stack(fast), axis=0) if fast else np.full(len(directions()), np.inf)
    s = np.max(np.stack(slow), axis=0)
    best = np.minimum(f, s)
    route = "fast" if np.median(f) <= np.median(s) else "slow"
    return Floor(float(np.median(best)), float(best.min()), float(best.max()), route)
