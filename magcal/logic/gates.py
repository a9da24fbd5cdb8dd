"""The gates a calibration must pass before it is written: the thresholds (``Gates``, a value
read from the configuration) and the verdicts (``GateResult``, one per gate, as data).

Every path that writes a calibration judges it here, so a gate means the same everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError


@dataclass(frozen=True)
class Gates:
    """What a calibration must show before it is written."""

    min_samples: int = 300  # samples kept for the fit (direction-balanced)
    min_coverage: float = 0.55  # share of the 128 equal-area direction cells visited
    max_rms_ut: float = 2.0  # RMS of |calibrated| − field over the kept samples
    field_range_ut: tuple = (15.0, 100.0)  # accepted field radius (Earth: 22–67 µT)
    max_offset_ut: float = 1000.0  # |offset| beyond this is a magnet, not hard iron
    max_offset_sigma_ut: float = 0.5  # 1σ uncertainty of each offset axis
    max_condition: float = 300.0  # of the normal matrix: thin coverage ⇒ large

    def check(self) -> None:
        lo, hi = self.field_range_ut
        if not 0 < lo < hi:
            raise ConfigError(f"gates.field_range_ut must be two increasing positive numbers, got {self.field_range_ut}")
        if not 0 < self.min_coverage <= 1:
            raise ConfigError(f"gates.min_coverage must be in (0, 1], got {self.min_coverage}")
        if self.min_samples < 10:
            raise ConfigError(f"gates.min_samples must be at least 10, got {self.min_samples}")



@dataclass(frozen=True)
class GateResult:
    name: str
    passed: bool
    value: float | None
    limit: object
    message: str

    def to_dict(self) -> dict:
        return {"gate": self.name, "passed": self.passed, "value": self.value, "limit": self.limit, "message": self.message}



def model_gates(g: Gates, offset_ut, field_ut, rms_ut, sigma_ut) -> list[GateResult]:
    """The gates a fitted calibration must pass before it is written, judged on its offset,
    field radius, residual RMS and offset uncertainty (1σ per axis)."""
    lo, hi = g.field_range_ut
    off = float(np.linalg.norm(offset_ut))
    sig = float(np.max(sigma_ut))
    return [
        GateResult("field_range", lo <= field_ut <= hi, float(field_ut), [lo, hi],
                   f"field radius {field_ut:.1f} µT (accepted {lo:g}–{hi:g})"),
        GateResult("max_offset", off <= g.max_offset_ut, off, g.max_offset_ut,
                   f"|offset| {off:.1f} µT (≤ {g.max_offset_ut:g})"),
        GateResult("max_rms", rms_ut <= g.max_rms_ut, float(rms_ut), g.max_rms_ut,
                   f"residual RMS {rms_ut:.2f} µT (≤ {g.max_rms_ut:g})"),
        GateResult("max_offset_sigma", sig <= g.max_offset_sigma_ut, sig, g.max_offset_sigma_ut,
                   f"offset uncertainty {sig:.3f} µT 1σ (≤ {g.max_offset_sigma_ut:g})"),
    ]

