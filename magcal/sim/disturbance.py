"""Intermittent disturbances of the field's magnitude: iron moved near the sensor and away, a
current switched on for a while, a passing vehicle.

Real residuals have heavier tails than any stationary Gaussian wander makes (docs/sensor-model.md):
stretches of a few samples to several seconds where |field| departs by many times the noise,
then comes back. The model: events arrive at random (Poisson, ``rate_per_s``); each holds the
field's magnitude away by a size drawn log-uniform in ``size_ut`` (up with probability
``up_share``, else down) for a duration drawn log-uniform in ``duration_s``, then lets go — or,
with ``events`` (pairs of size µT and duration s, the ones a recording showed), by the size and
for the duration of one pair drawn at random: sizes and durations drawn apart lose how they go
together, and a log-uniform range cut at its 5–95 % quantiles loses the few longest holds,
which carry most of the power.

``draw`` is a deterministic function of (seed, t): time is cut into cells as long as the
longest event, each cell's events are drawn from a generator keyed by (seed, cell), and a time
sees the events of its own cell and the one before — so the simulated board can be sampled at
any time, in any order, and reproduced, and a twin of a recording draws the same way.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

_KEY = 0xD157
_CELL_OFFSET = 1 << 40  # cells before t = 0 still key a non-negative seed
_KEEP = 16  # draws kept (``_kept``): a twin learner's seeds for one recording
_KEEP_VALUES = 1 << 22  # and no more values than this among them (32 MB): a long flight log keeps fewer
_KEPT: dict = {}


def _kept(key: tuple, make) -> np.ndarray:
    """A copy of the draw kept under ``key``, made by ``make()`` when it is not among the last
    _KEEP. The draw is a pure function of its key; a twin learner asks for the same one many
    times (the glitch rate's bisection draws the same four seeds' twins at each step, the
    disturbances the same in every one), and on a model whose events last a read it keys a
    generator per read — most of a learn from a glitchy recording."""
    out = _KEPT.pop(key, None)
    if out is None:
        out = make()
    _KEPT[key] = out
    while len(_KEPT) > 1 and (len(_KEPT) > _KEEP or sum(v.size for v in list(_KEPT.values())) > _KEEP_VALUES):
        _KEPT.pop(list(_KEPT)[0], None)  # the one asked for longest ago
    return out.copy()


def _generator(key: tuple) -> np.random.Generator:
    """``np.random.default_rng(list(key))`` (non-negative ints), its SeedSequence given the
    32-bit words it splits each int into (low word first, one 0 word for 0): the same generator,
    made in ~60 % of the time — a draw makes one per cell, and a cell can be a single read."""
    words = []
    for n in key:
        if n < 0:
            raise ValueError(f"a generator key is non-negative, got {n}")
        words.append(n & 0xFFFFFFFF)
        n >>= 32
        while n > 0:
            words.append(n & 0xFFFFFFFF)
            n >>= 32
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(np.array(words, dtype=np.uint32))))


@dataclass(frozen=True)
class Disturbances:
    rate_per_s: float
    size_ut: tuple
    duration_s: tuple
    up_share: float = 0.5
    events: tuple = ()

    def __post_init__(self):
        s = tuple(float(v) for v in self.size_ut)
        d = tuple(float(v) for v in self.duration_s)
        if len(s) != 2 or len(d) != 2:
            raise ValueError("disturbance size_ut and duration_s are (low, high) pairs")
        if not (np.isfinite(self.rate_per_s) and self.rate_per_s >= 0):
            raise ValueError(f"disturbance rate_per_s must be ≥ 0, got {self.rate_per_s}")
        if not (0 < s[0] <= s[1] < np.inf) or not (0 < d[0] <= d[1] < np.inf):
            raise ValueError(f"disturbance sizes and durations must be 0 < low ≤ high, got {list(s)}, {list(d)}")
        if not (0 <= self.up_share <= 1):
            raise ValueError(f"disturbance up_share must be in [0, 1], got {self.up_share}")
        ev = tuple((float(a), float(b)) for a, b in self.events)
        if any(not (0 < a < np.inf and 0 < b <= d[1] * (1 + 1e-9)) for a, b in ev):
            raise ValueError(f"disturbance events are (size_ut, duration_s) pairs > 0 lasting at most duration_s[1] = {d[1]}")
        object.__setattr__(self, "events", ev)
        object.__setattr__(self, "size_ut", s)
        object.__setattr__(self, "duration_s", d)
        object.__setattr__(self, "rate_per_s", float(self.rate_per_s))
        object.__setattr__(self, "up_share", float(self.up_share))

    def to_dict(self) -> dict:
        d = {"rate_per_s": self.rate_per_s, "size_ut": list(self.size_ut),
             "duration_s": list(self.duration_s), "up_share": self.up_share}
        if self.events:
            d["events"] = {"size_ut": [a for a, _ in self.events], "duration_s": [b for _, b in self.events]}
        return d

    @classmethod
    def from_dict(cls, d) -> "Disturbances":
        ev = d.get("events") or {}
        sizes, durations = list(ev.get("size_ut", ())), list(ev.get("duration_s", ()))
        if len(sizes) != len(durations):
            raise ValueError("disturbance events need as many size_ut as duration_s")
        return cls(rate_per_s=d["rate_per_s"], size_ut=tuple(d["size_ut"]), duration_s=tuple(d["duration_s"]),
                   up_share=d.get("up_share", 0.5), events=tuple(zip(sizes, durations)))

    def _cell_events(self, seed: int, cell: int, width: float) -> np.ndarray:
        """(k, 3): start, duration and signed size of the events starting in one cell."""
        rng = _generator((int(seed) & 0xFFFFFFFF, _KEY, cell + _CELL_OFFSET))
        k = rng.poisson(self.rate_per_s * width)
        if k == 0:  # most cells of a short-event model: no further draws (their values went unused)
            return np.zeros((0, 3))
        start = (cell + rng.random(k)) * width
        if self.events:
            pair = np.asarray(self.events)[rng.integers(0, len(self.events), k)]
            size = pair[:, 0] * np.where(rng.random(k) < self.up_share, 1.0, -1.0)
            return np.column_stack([start, pair[:, 1], size])
        dur = np.exp(rng.uniform(*np.log(self.duration_s), k))
        size = np.exp(rng.uniform(*np.log(self.size_ut), k)) * np.where(rng.random(k) < self.up_share, 1.0, -1.0)
        return np.column_stack([start, dur, size])

    def draw(self, seed: int, t_s) -> np.ndarray:
        """(n,) µT added to the field's magnitude at times ``t_s``."""
        t = np.ascontiguousarray(np.atleast_1d(np.asarray(t_s, dtype=np.float64)))
        if self.rate_per_s <= 0 or not len(t):
            return np.zeros(len(t))
        times = hashlib.sha256(t.tobytes()).digest()
        return _kept((self, int(seed), len(t), times), lambda: self._draw(seed, t))

    def _draw(self, seed: int, t: np.ndarray) -> np.ndarray:
        """``draw`` made afresh (``t`` float64, not empty)."""
        out = np.zeros(len(t))
        width = self.duration_s[1]
        order = np.argsort(t, kind="stable")
        ts = t[order]
        cells = np.unique(np.floor(ts / width).astype(np.int64))
        cells = np.unique(np.concatenate([cells - 1, cells]))
        ev = [self._cell_events(seed, int(c), width) for c in cells]
        ev = np.concatenate(ev) if ev else np.zeros((0, 3))
        lo = np.searchsorted(ts, ev[:, 0], side="left")
        hi = np.searchsorted(ts, ev[:, 0] + ev[:, 1], side="left")
        step = np.zeros(len(ts) + 1)
        np.add.at(step, lo, ev[:, 2])
        np.add.at(step, hi, -ev[:, 2])
        level = np.cumsum(step)[:-1]
        level[np.abs(level) < 1e-9 * self.size_ut[0]] = 0.0  # where every event has ended: exactly none
        out[order] = level
        return out
