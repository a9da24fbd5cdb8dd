"""Sample: one magnetometer reading as the host sees it (a value, no behaviour).

Units are in the names: ``field_ut`` is the ASA-adjusted field in µT in the AK8975 frame,
``raw`` the signed data-register counts as they came off the wire, ``t_s`` device time in
seconds, ``temp_c`` the IMU's die temperature (each chip's own formula, ``magcal.core.chips``). ``aux`` carries other channels by name
(``current_a`` ...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from .chips import MPU9150, Chip

# AK8975: 0.3 µT per LSB before sensitivity adjustment (datasheet MS1187-E-02).
UT_PER_COUNT = MPU9150.ut_per_count
ST2_DERR = 0x04
ST2_HOFL = 0x08
COUNT_MIN, COUNT_MAX = MPU9150.count_min, MPU9150.count_max


def asa_gain(asa: int) -> float:
    """Sensitivity adjustment factor H_adj/H = (ASA + 128) / 256 (0.5 … 1.5)."""
    return (int(asa) + 128) / 256.0


def counts_to_ut(raw, asa) -> np.ndarray:
    """Raw counts (…, 3) → ASA-adjusted µT (…, 3), float64."""
    gains = np.array([asa_gain(a) for a in asa], dtype=np.float64)
    return np.asarray(raw, dtype=np.float64) * (UT_PER_COUNT * gains)


def temp_raw_to_c(raw: int | float, chip: Chip = MPU9150) -> float:
    """TEMP_OUT → °C with ``chip``'s formula (``Chip.temp_c``)."""
    return float(chip.temp_c(float(raw)))


def temp_c_to_raw(temp_c: float, chip: Chip = MPU9150) -> int:
    """°C → the TEMP_OUT count ``chip`` reports (``Chip.temp_raw``)."""
    return chip.temp_raw(temp_c)


def raw_is_valid(raw, st2: int, chip: Chip = MPU9150) -> bool:
    """False for overflow/read-error flags, values on ``chip``'s rails and the all-zero triple."""
    if st2 & (ST2_DERR | ST2_HOFL):
        return False
    if chip.on_rail(raw):
        return False
    return any(v != 0 for v in raw)


@dataclass(frozen=True, slots=True)
class Sample:
    seq: int
    t_s: float
    field_ut: tuple[float, float, float]
    raw: tuple[int, int, int] | None = None
    st2: int = 0
    temp_c: float | None = None
    aux: Mapping[str, float] = field(default_factory=dict)
    chip: Chip = MPU9150  # the part that read it: its rails judge ``raw``

    @property
    def valid(self) -> bool:
        if self.raw is None:
            return not (self.st2 & (ST2_DERR | ST2_HOFL))
        return raw_is_valid(self.raw, self.st2, self.chip)

