"""The sensor's noise law: how its white noise and its slow noise (the wander) are distributed,
their σ and spectra aside.

**White noise.** 
A read's noise on axis a is σ_a · s · z_a — z standard normal per axis, s the read's noise
level, shared by its three axes: a Gaussian scale mixture. ln s is normal with standard
deviation ``level_sd`` (nepers) and mean −level_sd², so E[s²] = 1 and σ stays what it was, the
noise's RMS; the noise's kurtosis is 3·exp(4·level_sd²). A conversion whose noise level varies
from read to read — the reference or supply noise the three channels share, burst (popcorn)
noise — has such heavy tails: for the same RMS, more reads near zero and more far out.
``level_sd`` 0 is Gaussian white noise, drawn bit for bit as without a law.

| level_sd | 0 | 0.2 | 0.4 | 0.6 | 0.8 |
|---|---|---|---|---|---|
| 99th over 50th percentile of |noise| | 3.82 | 4.3 | 5.7 | 8.1 | 12.0 |

**Wander.** The offset and field wander (``magcal.sim.wander``) are drawn as stationary
Gaussian processes; a sensor's slow noise often makes larger excursions than a Gaussian of the
same spectrum level (a magnetised part that relaxes in bursts, a drifting reference that
sometimes runs away). With ``wander_h`` > 0 each wander value w (stationary σ: x = w/σ) is
seen through Tukey's h transform, w·exp(h·x²/2)·(1 − 2h)^¾: monotone and memoryless, so the
path keeps its times of rise and fall, E[w²] is kept (σ keeps its meaning), and its
99th-over-50th percentile ratio of |w| is 3.82·exp(3.09·h). 0 is the Gaussian wander.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from . import wander as wander_mod

LEVEL_SD_MAX = 1.5  # nepers: a kurtosis of 3·e⁹ ≈ 24 000, far beyond any sensor's white noise
WANDER_H_MAX = 0.49  # Tukey's h: the variance is finite below 0.5


@dataclass(frozen=True)
class NoiseLaw:
    """The distribution of each read's white noise (Gaussian unless ``level_sd`` > 0)."""

    level_sd: float = 0.0  # standard deviation of ln(noise level) per read, nepers
    wander_h: float = 0.0  # Tukey's h of the wander's excursions (0: a Gaussian wander)

    def __post_init__(self):
        v, h = float(self.level_sd), float(self.wander_h)
        if not (np.isfinite(v) and 0.0 <= v <= LEVEL_SD_MAX):
            raise ValueError(f"noise_law level_sd must be in [0, {LEVEL_SD_MAX}] nepers, got {self.level_sd!r}")
        if not (np.isfinite(h) and 0.0 <= h <= WANDER_H_MAX):
            raise ValueError(f"noise_law wander_h must be in [0, {WANDER_H_MAX}], got {self.wander_h!r}")
        object.__setattr__(self, "level_sd", v)
        object.__setattr__(self, "wander_h", h)

    @property
    def gaussian(self) -> bool:
        return self.level_sd == 0.0 and self.wander_h == 0.0

    @property
    def kurtosis(self) -> float:
        """E[x⁴]/E[x²]² of one axis's noise: 3 for Gaussian noise."""
        return 3.0 * float(np.exp(4.0 * self.level_sd**2))

    def levels(self, w) -> np.ndarray:
        """Each read's noise level s = exp(level_sd·w − level_sd²) from standard normals ``w``
        (one per read): E[s²] = 1. Smooth in level_sd for fixed ``w``, so twins drawn on the
        same seeds move smoothly as the law is learned."""
        w = np.asarray(w, dtype=np.float64)
        return np.exp(self.level_sd * w - self.level_sd**2) if self.level_sd else np.ones_like(w)

    def wander(self, components, offset_ut: np.ndarray, field_ut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset (n, 3), field (n,)) µT: the Gaussian wander paths drawn for ``components``
        (``magcal.sim.wander``) seen through Tukey's h transform, each axis and the field
        against its own stationary σ; as they are for a Gaussian wander."""
        if self.wander_h == 0.0:
            return offset_ut, field_ut
        offset, field = wander_mod.split(components)
        sd_offset = np.sqrt(np.sum([np.square(c.sigma_ut) for c in offset], axis=0)) if offset else np.zeros(3)
        sd_field = float(np.sqrt(sum(c.sigma_ut[0] ** 2 for c in field)))
        return self._excursions(offset_ut, sd_offset), self._excursions(field_ut, sd_field)

    def _excursions(self, w: np.ndarray, sd) -> np.ndarray:
        h = self.wander_h
        sd = np.asarray(sd, dtype=np.float64)
        x = w / np.where(sd > 0, sd, 1.0)
        return w * np.exp(0.5 * h * x * x) * (1.0 - 2.0 * h) ** 0.75

    def to_dict(self) -> dict:
        return {"level_sd": self.level_sd, "wander_h": self.wander_h}

    @classmethod
    def from_dict(cls, d: Mapping | None) -> "NoiseLaw":
        """The law from ``to_dict``'s shape (None or absent: Gaussian); ValueError naming the
        problem otherwise."""
        if d is None:
            return cls()
        if not isinstance(d, Mapping):
            raise ValueError("noise_law is a mapping (level_sd: nepers, wander_h)")
        unknown = set(d) - {"level_sd", "wander_h"}
        if unknown:
            raise ValueError(f"noise_law has unknown keys {sorted(unknown)} (known: level_sd, wander_h)")
        values = {}
        for key in ("level_sd", "wander_h"):
            try:
                values[key] = float(d.get(key, 0.0))
            except (TypeError, ValueError):
                raise ValueError(f"noise_law {key} must be a number, got {d.get(key)!r}") from None
        return cls(**values)
