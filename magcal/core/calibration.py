"""Calibration: the model that maps a measured field to the true one, as a value.

Forward model (what the sensor does), sensor frame, µT::

    m = W⁻¹ h + offset_ut + Σ_c coef[c] · (x_c − ref[c])

Correction (what we apply)::

    h = soft_iron @ (m − offset_ut − Σ_c coef[c] · (x_c − ref[c]))

``soft_iron`` is W, symmetric positive definite; ``field_ut`` the expected |h|. ``coef_ut_per_unit``
maps a channel name (``temp_c``, ``current_a``, ``t_s`` …) to three µT-per-unit coefficients;
``reference`` maps a channel to its reference value (a channel without one is taken at 0).

>>> import numpy as np
>>> cal = Calibration(offset_ut=[10.0, -5.0, 2.0], field_ut=50.0)
>>> h = np.array([[50.0, 0.0, 0.0]])
>>> bool(np.allclose(cal.correct(cal.distort(h)), h))
True
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Mapping

import numpy as np


# The field a magnetometer at the Earth's surface sees: 22–67 µT by the World Magnetic Model,
# widened for nearby iron. A fitted field outside it is a wrong unit or a wrong solution.
EARTH_FIELD_UT = (15.0, 100.0)


def _vec3(v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    a.setflags(write=False)
    return a


def _mat3(m) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64).reshape(3, 3)
    a = 0.5 * (a + a.T)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Calibration:
    offset_ut: np.ndarray
    field_ut: float
    soft_iron: np.ndarray = field(default_factory=lambda: np.eye(3))
    coef_ut_per_unit: Mapping[str, np.ndarray] = field(default_factory=dict)
    reference: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "offset_ut", _vec3(self.offset_ut))
        object.__setattr__(self, "soft_iron", _mat3(self.soft_iron))
        object.__setattr__(self, "field_ut", float(self.field_ut))
        object.__setattr__(
            self, "coef_ut_per_unit", {k: _vec3(v) for k, v in dict(self.coef_ut_per_unit).items()}
        )
        object.__setattr__(self, "reference", {k: float(v) for k, v in dict(self.reference).items()})
        if not np.all(np.isfinite(self.offset_ut)) or not np.isfinite(self.field_ut):
            raise ValueError("calibration offset and field must be finite")
        if not self.field_ut > 0:
            raise ValueError(f"the field radius must be positive, got {self.field_ut:g} µT")
        if np.any(np.linalg.eigvalsh(self.soft_iron) <= 0):
            raise ValueError("soft_iron must be positive definite")

    # -- the model -----------------------------------------------------------------------
    def channel_offset_ut(self, channels: Mapping[str, np.ndarray] | None, n: int) -> np.ndarray:
        """Σ coef·(x − ref) as an (n, 3) array; channels missing from ``channels`` count as ref."""
        total = np.zeros((n, 3))
        for name, coef in self.coef_ut_per_unit.items():
            if channels is None or name not in channels:
                continue
            x = np.asarray(channels[name], dtype=np.float64).reshape(-1)
            total += np.outer(x - self.reference.get(name, 0.0), coef)
        return total

    def correct(self, m_ut, channels: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Measured (n, 3) µT → calibrated (n, 3) µT."""
        m = np.atleast_2d(np.asarray(m_ut, dtype=np.float64))
        d = m - self.offset_ut - self.channel_offset_ut(channels, len(m))
        return d @ self.soft_iron.T

    def distort(self, h_ut, channels: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """True (n, 3) µT → what the sensor would measure: the forward model."""
        h = np.atleast_2d(np.asarray(h_ut, dtype=np.float64))
        return (
            np.linalg.solve(self.soft_iron, h.T).T
            + self.offset_ut
            + self.channel_offset_ut(channels, len(h))
        )

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = {
            "offset_ut": [float(v) for v in self.offset_ut],
            "field_ut": float(self.field_ut),
            "soft_iron": [[float(v) for v in row] for row in self.soft_iron],
        }
        if self.coef_ut_per_unit:
            d["coef_ut_per_unit"] = {k: [float(x) for x in v] for k, v in self.coef_ut_per_unit.items()}
        if self.reference:
            d["reference"] = dict(self.reference)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "Calibration":
        return cls(
            offset_ut=d["offset_ut"],
            field_ut=d["field_ut"],
            soft_iron=d.get("soft_iron", np.eye(3)),
            coef_ut_per_unit=d.get("coef_ut_per_unit", {}),
            reference=d.get("reference", {}),
        )

    def close_to(self, other: "Calibration", atol_ut: float = 1e-3, atol_w: float = 1e-6) -> bool:
        """Equal within the given tolerances (used to compare a read-back with what was sent)."""
        keys = set(self.coef_ut_per_unit) | set(other.coef_ut_per_unit)
        z = np.zeros(3)
        return bool(
            np.allclose(self.offset_ut, other.offset_ut, atol=atol_ut, rtol=0)
            and abs(self.field_ut - other.field_ut) <= atol_ut
            and np.allclose(self.soft_iron, other.soft_iron, atol=atol_w, rtol=0)
            and all(
                np.allclose(self.coef_ut_per_unit.get(k, z), other.coef_ut_per_unit.get(k, z), atol=atol_ut, rtol=0)
                for k in keys
            )
        )


class RecordState(str, Enum):
    """What a device's calibration store holds."""

    NONE = "none"  # nothing stored (a blank store)
    OK = "ok"  # a calibration
    CORRUPT = "corrupt"  # fails its own check (format, version, CRC): the device does not apply it
    INVALID = "invalid"  # passes its check but is no calibration (a matrix that is not positive definite …)


@dataclass(frozen=True)
class StoredRecord:
    """A device's store as read: the calibration, or the state it is in and why it cannot be used."""

    state: RecordState
    calibration: Calibration | None = None
    problem: str = ""

    def to_dict(self) -> dict:
        return {"state": self.state.value, "problem": self.problem or None}
