"""The chips magcal knows: each IMU with its magnetometer, as one table of datasheet facts.

A ``Chip`` says how to recognise a part (the IMU's ``WHO_AM_I``, the magnetometer's device id),
what one count is worth (``ut_per_count``), the counts the data registers can hold, whether the
part has per-axis sensitivity adjustment (ASA) bytes, the self-test pass window (which depends on
the output resolution) and the time one measurement takes. Every other module that needs one of
these numbers takes it from here, so a new part is one row.

Sources (each figure below names its own):
- AK8975: AKM datasheet MS1187-E-02 (inside the MPU-9150; MPU-9150 register map RM-MPU-9150A-00).
- AK8963: AKM datasheet MS1356-E-02 (inside the MPU-9250/9255; register map RM-MPU-9250A-00).
- AK09916: AKM datasheet AK09916C 015007392-E-02 (inside the ICM-20948; InvenSense DS-000189).

The magnetometer die sits in the package turned against the IMU, so its axes are not the
accelerometer's: ``mag_from_accel`` is that turn as a signed permutation, the one place the fact
lives (the host turns the accelerometer into the magnetometer's frame; the simulated boards turn
the physics' body frame, which is the magnetometer's, back into the IMU's).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

Window = tuple[tuple[int, int], tuple[int, int], tuple[int, int]]
AxisMap = tuple[tuple[int, int], tuple[int, int], tuple[int, int]]  # per magnetometer axis: (accelerometer axis, sign)

# The orientation-of-axes figures (accelerometer/gyroscope and magnetometer drawn on the package):
# MPU-9150 product specification PS-MPU-9150A-00 and MPU-9250 PS-MPU-9250A-01 — the AK8975/AK8963
# has X along the accelerometer's Y, Y along its X, Z opposite its Z (a left-right swap of X and Y
# keeps the magnetometer right-handed only with Z flipped); ICM-20948 DS-000189 §11.1 — the AK09916
# has X along the accelerometer's X, Y and Z opposite its Y and Z.
AK89XX_IN_MPU = ((1, +1), (0, +1), (2, -1))  # mag X = accel Y, mag Y = accel X, mag Z = −accel Z
AK09916_IN_ICM = ((0, +1), (1, -1), (2, -1))  # mag X = accel X, mag Y = −accel Y, mag Z = −accel Z


class Magnetometer(Enum):
    """The AKM die inside the package."""

    AK8975 = "AK8975"
    AK8963 = "AK8963"
    AK09916 = "AK09916"


@dataclass(frozen=True)
class Chip:
    """One IMU + magnetometer at one output resolution."""

    name: str  # the option value: mpu9150, mpu9250, icm20948
    label: str  # what show/calibrate/the report print
    magnetometer: Magnetometer
    who_am_i: tuple[int, ...]  # the IMU's WHO_AM_I values that mean this part
    mag_id: int  # WIA (AK8975/AK8963) or WIA2 (AK09916)
    bits: int  # output resolution the data registers are read at
    ut_per_count: float  # µT per count before any sensitivity adjustment
    count_min: int
    count_max: int
    has_asa: bool  # per-axis sensitivity adjustment bytes in fuse ROM
    self_test_window: Window  # pass window per axis, in (ASA-adjusted) counts
    measurement_s: float  # worst-case single-measurement time
    overflow_sum_ut: float  # ST2 HOFL is set when |X|+|Y|+|Z| reaches this
    self_test_typical: tuple[int, int, int]  # a healthy coil's reading, inside the window
    temp_lsb_per_c: float  # the IMU's die temperature: T = TEMP_OUT / temp_lsb_per_c + temp_offset_c
    temp_offset_c: float
    mag_from_accel: AxisMap  # the accelerometer's axes → the magnetometer's (a signed permutation)

    def accel_to_mag(self, accel):
        """Accelerometer readings (..., 3), the IMU's own axes → the magnetometer's axes (same unit)."""
        a = np.asarray(accel, dtype=np.float64)
        return np.stack([sign * a[..., k] for k, sign in self.mag_from_accel], axis=-1)

    def mag_to_accel(self, vector):
        """Vectors (..., 3) in the magnetometer's axes → the accelerometer's (``accel_to_mag`` undone)."""
        v = np.asarray(vector, dtype=np.float64)
        out = np.empty_like(v)
        for i, (k, sign) in enumerate(self.mag_from_accel):
            out[..., k] = sign * v[..., i]
        return out

    @property
    def range_ut(self) -> float:
        """The largest field one axis can report, µT."""
        return float(self.count_max) * self.ut_per_count

    def counts_in_range(self, value: int) -> bool:
        return self.count_min <= int(value) <= self.count_max

    def on_rail(self, raw) -> bool:
        """True when a count sits at or past either end of the range (a clipped axis)."""
        return any(v <= self.count_min or v >= self.count_max for v in raw)

    def temp_c(self, temp_raw):
        """TEMP_OUT (a signed count, or an array of them) → die temperature, °C."""
        return temp_raw / self.temp_lsb_per_c + self.temp_offset_c

    def temp_raw(self, temp_c: float) -> int:
        """Die temperature, °C → the TEMP_OUT count this part reports (16-bit signed)."""
        return int(min(max(round((float(temp_c) - self.temp_offset_c) * self.temp_lsb_per_c), -32768), 32767))


MPU9150 = Chip(
    name="mpu9150", label="MPU-9150 (AK8975, 13-bit)", magnetometer=Magnetometer.AK8975,
    who_am_i=(0x68,),  # RM-MPU-9150A-00 WHO_AM_I 0x75 = 0x68
    mag_id=0x48,  # MS1187-E-02 WIA 0x00 = 0x48
    bits=13,
    ut_per_count=0.3,  # MS1187-E-02 sensitivity 0.3 µT/LSB
    count_min=-4096, count_max=4095,  # MS1187-E-02 measurement data output range (two's complement, 13 bit)
    has_asa=True,  # MS1187-E-02 ASAX/Y/Z fuse ROM 0x10-0x12
    self_test_window=((-100, 100), (-100, 100), (-1000, -300)),  # MS1187-E-02 self-test judgement
    measurement_s=0.009,  # MS1187-E-02 single measurement time max 9 ms
    overflow_sum_ut=2400.0,  # MS1187-E-02 ST2 HOFL: |X|+|Y|+|Z| >= 2400 µT
    self_test_typical=(12, -18, -640),
    temp_lsb_per_c=340.0, temp_offset_c=36.53,  # RM-MPU-9150A-00 TEMP_OUT: raw / 340 + 36.53 °C
    mag_from_accel=AK89XX_IN_MPU,
)


def _mpu9250(bits: int) -> Chip:
    sixteen = bits == 16
    return Chip(
        name="mpu9250", label=f"MPU-9250/9255 (AK8963, {bits}-bit)", magnetometer=Magnetometer.AK8963,
        who_am_i=(0x71, 0x73),  # RM-MPU-9250A-00 WHO_AM_I 0x75 = 0x71; MPU-9255 reads 0x73
        mag_id=0x48,  # MS1356-E-02 WIA 0x00 = 0x48
        bits=bits,
        ut_per_count=0.15 if sixteen else 0.6,  # MS1356-E-02: 0.15 µT/LSB (16-bit), 0.6 µT/LSB (14-bit)
        # MS1356-E-02 measurement data output range: ±32760 (16-bit), ±8190 (14-bit)
        count_min=-32760 if sixteen else -8190, count_max=32760 if sixteen else 8190,
        has_asa=True,  # MS1356-E-02 ASAX/Y/Z fuse ROM 0x10-0x12
        # MS1356-E-02 self-test judgement: 16-bit X,Y ±200, Z -3200…-800; 14-bit X,Y ±50, Z -800…-200
        self_test_window=((-200, 200), (-200, 200), (-3200, -800)) if sixteen else ((-50, 50), (-50, 50), (-800, -200)),
        measurement_s=0.009,  # MS1356-E-02 single measurement time max 9 ms (typ 7.2 ms)
        overflow_sum_ut=4912.0,  # MS1356-E-02 ST2 HOFL: |X|+|Y|+|Z| >= 4912 µT
        self_test_typical=(48, -72, -2000) if sixteen else (12, -18, -500),
        temp_lsb_per_c=333.87, temp_offset_c=21.0,  # RM-MPU-9250A-00 TEMP_OUT: raw / 333.87 + 21 °C
        mag_from_accel=AK89XX_IN_MPU,
    )


MPU9250_16 = _mpu9250(16)
MPU9250_14 = _mpu9250(14)

ICM20948 = Chip(
    name="icm20948", label="ICM-20948 (AK09916, 16-bit)", magnetometer=Magnetometer.AK09916,
    who_am_i=(0xEA,),  # DS-000189 bank 0 WHO_AM_I 0x00 = 0xEA
    mag_id=0x09,  # 015007392-E-02 WIA2 0x01 = 0x09 (WIA1 0x00 = 0x48, the company id)
    bits=16,
    ut_per_count=0.15,  # 015007392-E-02 sensitivity 0.15 µT/LSB
    count_min=-32752, count_max=32752,  # 015007392-E-02 measurement data output range ±32752
    has_asa=False,  # the AK09916 has no fuse-ROM sensitivity adjustment (read as ASA 128 = factor 1)
    self_test_window=((-200, 200), (-200, 200), (-1000, -200)),  # 015007392-E-02 self-test judgement
    measurement_s=0.0085,  # 015007392-E-02 single measurement time max 8.5 ms
    overflow_sum_ut=4912.0,  # 015007392-E-02 ST2 HOFL: |X|+|Y|+|Z| >= 4912 µT
    self_test_typical=(24, -36, -600),
    temp_lsb_per_c=333.87, temp_offset_c=21.0,  # DS-000189 TEMP_OUT: raw / 333.87 + 21 °C
    mag_from_accel=AK09916_IN_ICM,
)

CHIPS: tuple[Chip, ...] = (MPU9150, MPU9250_16, MPU9250_14, ICM20948)
CHIP_NAMES: tuple[str, ...] = ("mpu9150", "mpu9250", "icm20948")
DEFAULT = MPU9150
NEUTRAL_ASA = (128, 128, 128)  # what a part without ASA reports: factor (128+128)/256 = 1


def chip_named(name: str, bits: int | None = None) -> Chip:
    """The table row for an option value (``mpu9250`` takes ``bits`` 14 or 16, default 16)."""
    key = str(name).strip().lower().replace("-", "")
    matches = [c for c in CHIPS if c.name == key]
    if not matches:
        raise ValueError(f"unknown chip {name!r}: expected one of {', '.join(CHIP_NAMES)}")
    if bits is None:
        return matches[0]
    for chip in matches:
        if chip.bits == int(bits):
            return chip
    allowed = "/".join(str(c.bits) for c in matches)
    raise ValueError(f"chip {key} has no {bits}-bit output: expected bits={allowed}")


def chip_from_ids(who_am_i: int, mag_id: int, bits: int | None = None) -> Chip:
    """The part that answers with this IMU WHO_AM_I and magnetometer id (and resolution, if known)."""
    for chip in CHIPS:
        if int(who_am_i) in chip.who_am_i and int(mag_id) == chip.mag_id and (bits is None or chip.bits == int(bits)):
            return chip
    raise ValueError(
        f"no known chip answers WHO_AM_I 0x{int(who_am_i):02X} with magnetometer id 0x{int(mag_id):02X}"
        + (f" at {bits} bits" if bits is not None else "")
        + " (known: MPU-9150 0x68/0x48, MPU-9250 0x71 or 0x73/0x48, ICM-20948 0xEA/0x09)"
    )
