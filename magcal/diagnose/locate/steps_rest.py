"""What the change-point search (magcal.diagnose.locate.steps) leaves as the honest remainder:
stretches where the data misbehave, and offset jumps that undo each other.

- ``structure``: a stretch whose residual RMS, after the slow wander and any found step, stands
  ``STRUCTURE_OVER_TYPICAL`` times above the recording's typical window and
  ``STRUCTURE_OVER_FLOOR`` times above its floor, explained by no step.
- ``bursts``: found steps that come in a cluster and mostly undo each other — not a part put
  down, but the data misbehaving for a while.

Both are ``unexplained_structure`` located in time, sized against the recording's own floor.
The windows the stretches are measured in are ``STRUCTURE_WINDOW_S`` long on a recording with a
clock; without one (its t_s the sample index) seconds mean nothing, and the window keeps the
ratio it has to the step search's shortest window (``structure_window``).
"""

from __future__ import annotations

import numpy as np

from ..timewords import stretch
from . import steps_scan as scan
from .base import REST, Kind, Located, runs

BURST_NET = 0.5
STRUCTURE_OVER_TYPICAL = 3.0
STRUCTURE_OVER_FLOOR = 2.0
STRUCTURE_WINDOW_S = 1.0
SHORTEST_HALF_S = 3.0  # the step search's shortest half window with a clock (steps.HALF_RANGE_S[0])


def window(seconds: float, half: float, clock: bool) -> float:
    """A window of ``seconds`` in the units of t: itself with a clock; without one (t the sample
    index) the ratio it has to the step search's shortest half window, kept to ``half`` (the
    recording's own half window in samples, steps.half_window_s), and at least one sample."""
    return seconds if clock else max(half * seconds / SHORTEST_HALF_S, 1.0)


def structure_window(half: float, clock: bool) -> float:
    """The window a stretch's RMS is measured in (in the units of t: s, or samples without a clock)."""
    return window(STRUCTURE_WINDOW_S, half, clock)


def structure(u, t, r, half, floor_ut: float, window: float = STRUCTURE_WINDOW_S) -> list[Located]:
    """Stretches whose RMS residual (after the wander) stands far above the recording's typical
    window and its floor, explained by no step."""
    x = scan.wander_columns(u, t, half)
    e = r - x @ scan.lsq(x, r).coef
    edges = np.arange(t[0], t[-1] + window, window)
    cell = np.clip(np.searchsorted(edges, t, "right") - 1, 0, len(edges) - 1)
    n = np.bincount(cell, minlength=len(edges))
    ms = np.bincount(cell, e * e, minlength=len(edges)) / np.maximum(n, 1)
    rms = np.sqrt(ms)
    typical = float(np.median(rms[n >= 5])) if np.any(n >= 5) else 0.0
    bad = (n >= 5) & (rms > STRUCTURE_OVER_TYPICAL * typical) & (rms > STRUCTURE_OVER_FLOOR * floor_ut)
    out = []
    for a, b in _merged(runs(bad), int(np.ceil(half / window))):
        inside = (cell >= a) & (cell < b) & bad[cell]
        level = float(np.sqrt(np.mean(e[inside] ** 2)))
        t0, t1 = float(t[inside][0]), float(t[inside][-1])
        over = level / floor_ut
        summary = f"unexplained structure remains: {over:.1f}× the noise, at {stretch(t0, t1)}"
        out.append(Located(REST, Kind.REMAINDER, summary, {"time_s": [[t0, t1]]}, {"rms_ut": level},
                           {"size_over_floor": over, "typical_rms_ut": typical, "size_ut": level}))
    return out


def _merged(spans: list[tuple[int, int]], gap: int) -> list[tuple[int, int]]:
    """Runs closer than ``gap`` windows joined: one misbehaving stretch, not a list of its pieces."""
    out: list[tuple[int, int]] = []
    for a, b in spans:
        if out and a - out[-1][1] <= gap:
            out[-1] = (out[-1][0], b)
        else:
            out.append((a, b))
    return out


def bursts(steps: list, half: float, floor_ut: float) -> tuple[list, list[Located]]:
    """Steps (``steps.HardIronStep``) that come in a cluster (each within 2 windows of the next)
    and mostly undo each other (their sum under ``BURST_NET`` of the largest) are not a part put
    down: the data misbehave there for a while. Those are returned as the remainder, located in
    time — where the recording's floor was measured: a window no ellipsoid fits has no floor to
    size them against (its steps, likewise, are not claimed), and a jump "inf× the noise" says
    nothing. Returns (the steps kept, the remainder)."""
    groups: list[list] = []
    for s in steps:
        if groups and s.tau_s - groups[-1][-1].tau_s <= 2 * half:
            groups[-1].append(s)
        else:
            groups.append([s])
    keep, rest = [], []
    for g in groups:
        net = np.linalg.norm(sum(s.d_h for s in g))
        big = max(np.linalg.norm(s.d_h) for s in g)
        if len(g) < 2 or net >= BURST_NET * big:
            keep += g
            continue
        if not floor_ut > 0:
            continue
        t0, t1 = g[0].tau_s, g[-1].tau_s
        over = big / floor_ut
        summary = (f"unexplained structure remains: {over:.1f}× the noise, at {stretch(t0, t1)} "
                   f"(offset jumps that undo each other)")
        rest.append(Located(REST, Kind.REMAINDER, summary, {"time_s": [[t0, t1]]}, {"largest_jump_ut": big},
                            {"size_over_floor": over, "size_ut": big}))
    return keep, rest
