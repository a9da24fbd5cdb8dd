"""A recording made of takes: each placement of the board sits in its own hard-iron surroundings.

A recorder that pauses while the board is placed anew (gearvr Officemag: "pausing recording
when you change the orientation") gives a recording of takes — the board still within each,
turned between them. Each placement puts the board somewhere else on the desk, near other iron,
so each take's field magnitude sits at its own level (Officemag: levels spread about 1.5 µT
between takes against 0.2 µT within one; three takes 2–6 µT above the rest). A still board determines
only the level along its field direction, so a take's level is part of its calibration: every
refit of such a recording (the real one and each twin alike) removes a level per take, and its
wander is what is left within the takes.

``start_s``: the time each take after the first begins (a take holds the samples from its start
up to the next one's); ``level_sd_ut``: the spread of the levels between takes, which a twin
draws as one normal level per take from a generator of its own, so that the other random
parts of the twin do not move.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_KEY = 0x7A4E5


@dataclass(frozen=True)
class Takes:
    start_s: tuple
    level_sd_ut: float = 0.0

    def __post_init__(self):
        s = tuple(float(v) for v in self.start_s)
        if not s or not np.all(np.isfinite(s)) or any(b <= a for a, b in zip(s, s[1:])):
            raise ValueError("takes start_s must be one or more finite times, ascending")
        if not (np.isfinite(self.level_sd_ut) and self.level_sd_ut >= 0):
            raise ValueError(f"takes level_sd_ut must be ≥ 0, got {self.level_sd_ut}")
        object.__setattr__(self, "start_s", s)
        object.__setattr__(self, "level_sd_ut", float(self.level_sd_ut))

    @property
    def count(self) -> int:
        return len(self.start_s) + 1

    def index(self, t_s) -> np.ndarray:
        """(n,) the take each time belongs to (0 before the first start)."""
        return np.searchsorted(np.asarray(self.start_s), np.asarray(t_s, dtype=np.float64), side="right")

    def levels(self, seed: int, t_s) -> np.ndarray:
        """(n,) µT: the field magnitude's level of each sample's take, N(0, level_sd_ut²) per
        take from a generator of its own, keyed by the seed."""
        z = np.random.default_rng([int(seed) & 0xFFFFFFFF, _KEY]).standard_normal(self.count)
        return self.level_sd_ut * z[self.index(t_s)]

    def means(self, e: np.ndarray, t_s) -> np.ndarray:
        """(count,) the mean of ``e`` (at times ``t_s``) over each take (0 for one with none)."""
        k = self.index(t_s)
        return np.bincount(k, weights=e, minlength=self.count) / np.maximum(np.bincount(k, minlength=self.count), 1)

    def demean(self, e: np.ndarray, t_s) -> np.ndarray:
        """``e`` less each take's own mean (the level a refit removes per placement)."""
        return e - self.means(e, t_s)[self.index(t_s)]

    def to_dict(self) -> dict:
        return {"count": self.count, "start_s": list(self.start_s), "level_sd_ut": self.level_sd_ut}

    @classmethod
    def from_dict(cls, d) -> "Takes":
        try:
            return cls(start_s=tuple(d["start_s"]), level_sd_ut=float(d.get("level_sd_ut", 0.0)))
        except KeyError as exc:
            raise ValueError(f"takes lacks {exc.args[0]!r}") from None
