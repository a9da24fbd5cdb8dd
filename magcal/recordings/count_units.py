"""What one count of a common magnetometer is in µT: the units a file of raw counts may be in,
named when a fitted field is no Earth field (``table.plausible_field``)."""

from __future__ import annotations


# µT of one count of common magnetometers (datasheet sensitivities), to name what a file in
# raw counts would be: the ones that put a fitted field inside the Earth's 25–65 µT.
COUNT_UT = (
    ("AK8975 (MPU-9150)", 0.3), ("AK8963 16-bit (MPU-9250)", 0.15), ("AK8963 14-bit", 0.6),
    ("HMC5883L at 1090 LSB/G", 100 / 1090), ("QMC5883L at ±8 G", 100 / 3000), ("QMC5883L at ±2 G", 100 / 12000),
    ("LIS3MDL at ±4 G", 100 / 6842), ("MMC5883MA", 100 / 4096), ("LSM303AGR / LIS2MDL", 0.15),
)
SURFACE_FIELD_UT = (25.0, 65.0)


def count_guess(field_ut: float) -> str:
    """Which count sizes would make ``field_ut`` (read as µT) an Earth field, as ``--unit``
    values; always the one count size that makes it 50 µT (pure)."""
    lo, hi = SURFACE_FIELD_UT
    fits = [f"{name}: --unit {s:.4g} gives {field_ut * s:.1f} µT" for name, s in COUNT_UT if lo <= field_ut * s <= hi]
    mid = f"--unit {50.0 / field_ut:.3g} (µT per count) would make it 50 µT"
    return "; ".join(fits) + f" ({mid})" if fits else mid
