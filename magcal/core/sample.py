"""Sample: one magnetometer reading as the host sees it (a value, no behaviour).

Units are in the names: ``field_ut`` is the ASA-adjusted field in µT in the AK8975 frame,
``raw`` the signed data-register counts as they came off the wire, ``t_s`` device time in
seconds, ``temp_c`` the MPU die temperature. ``aux`` carries other channels by name
(``current_a`` ...).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

# AK8975: 0.3 µT per LSB before sensitivity adjustment (datasheet MS1187-E-02).
UT_PER_COUNT = 0.3
ST2_DERR = 0x04
ST2_HOFL = 0x08
COUNT_MIN, COUNT_MAX = -4096, 4095


def asa_gain(asa: int) -> float:
    """Sensitivity adjustment factor H_adj/H = (ASA + 128) / 256 (0.5 … 1.5)."""
    return (int(asa) + 128) / 256.0


def counts_to_ut(raw, asa) -> np.ndarray:
    """Raw counts (…, 3) → ASA-adjusted µT (…, 3), float64."""
    gains = np.array([asa_gain(a) for a in asa], dtype=np.float64)
    return np.asarray(raw, dtype=np.float64) * (UT_PER_COUNT * gains)


def temp_raw_to_c(raw: int | float) -> float:
    """MPU TEMP_OUT → °C with the MPU-6050 map (raw/340 + 36.53); only differences matter."""
    return float(raw) / 340.0 + 36.53


def temp_c_to_raw(temp_c: float) -> int:
    return int(round((temp_c - 36.53) * 340.0))


def raw_is_valid(raw, st2: int) -> bool:
    """False for overflow/read-error flags, rail values and the all-zero triple."""
    if st2 & (ST2_DERR | ST2_HOFL):
        return False
    if any(v <= COUNT_MIN or v >= COUNT_MAX for v in raw):
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

    @property
    def valid(self) -> bool:
        if self.raw is None:
            return not (self.st2 & (ST2_DERR | ST2_HOFL))
        return raw_is_valid(self.raw, self.st2)
