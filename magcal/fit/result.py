"""FitResult: what ``magcal.fit.fit`` returns when the data support a model."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np

from ..core.calibration import Calibration

MODEL_NAMES = {"sphere": "sphere", "diagonal": "ellipsoid_diagonal", "full": "ellipsoid"}


@dataclass(frozen=True)
class FitResult:
    """A fitted calibration with its uncertainty.

    ``model``: "sphere", "ellipsoid_diagonal" or "ellipsoid". ``calibration``: calibrated sample
    = soft_iron @ (m − offset_ut), |·| ≈ field_ut; soft_iron has det 1. ``uncertainty``: 1σ of
    offset_ut (3), field_ut and soft_iron (3×3): σ̂²(JᵀJ)⁻¹, or the block (batch-means) sandwich
    when correlated residuals make it larger, by ``autocorrelation_factor`` (√ of the ratio of
    the offset variances; 1 when the residuals look independent), and at least a jackknife over
    six direction groups (``direction_factor``: how much wider that made the offset's σ, ≥ 1)
    and a delete-a-block jackknife over eight contiguous time blocks (``time_block_factor``,
    likewise; ``uncertainty.summarise``). ``crlb_offset_ut``: √diag of the
    Cramér–Rao bound of the offset for this data's geometry (noise σ given, else σ̂).
    ``outliers``: indices into the input that were removed. ``reason``: why this model.
    ``residual_ut``: geometric residual of the samples used (in input order of ``used``).
    ``summary``: makes (``uncertainty``, ``crlb_offset_ut``) when first read — most of fit's
    runs inside a diagnosis (held-out blocks, fault screening, the locate step's judge) read
    only the calibration; where they are read they are the same numbers.
    """

    model: str
    calibration: Calibration
    summary: Callable[[], tuple[dict, np.ndarray]] = field(repr=False, compare=False)
    rms_ut: float
    n_used: int
    outliers: np.ndarray
    reason: str
    condition: float = float("nan")
    used: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    residual_ut: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    alternatives: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return True

    @cached_property
    def _summarised(self) -> tuple[dict, np.ndarray]:
        return self.summary()

    @property
    def uncertainty(self) -> dict:
        return self._summarised[0]

    @property
    def crlb_offset_ut(self) -> np.ndarray:
        return self._summarised[1]

    def to_dict(self) -> dict:
        cal = self.calibration
        u = self.uncertainty
        return {
            "model": self.model,
            "calibration": {
                "offset_ut": [float(v) for v in cal.offset_ut],
                "field_ut": float(cal.field_ut),
                "soft_iron": [[float(v) for v in row] for row in cal.soft_iron],
            },
            "uncertainty": {
                "offset_ut": [float(v) for v in u["offset_ut"]],
                "field_ut": float(u["field_ut"]),
                "soft_iron": [[float(v) for v in row] for row in np.asarray(u["soft_iron"])],
                "autocorrelation_factor": float(u.get("autocorrelation_factor", 1.0)),
                "direction_factor": float(u.get("direction_factor", 1.0)),
                "time_block_factor": float(u.get("time_block_factor", 1.0)),
            },
            "crlb_offset_ut": [float(v) for v in self.crlb_offset_ut],
            "rms_ut": float(self.rms_ut),
            "n_used": int(self.n_used),
            "outliers": [int(i) for i in self.outliers],
            "reason": self.reason,
            "condition": float(self.condition),
        }
