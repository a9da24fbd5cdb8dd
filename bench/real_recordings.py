"""Loaders for the real recordings in ../shared/data/real used by the diagnosis benchmark.

Each loader returns (t_s, field) with field in the recording's own units; the benchmark only
needs shapes and the trajectory, and rescales to µT itself. Columns and rates are those given
in each folder's PROVENANCE.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_ROOT = HERE.parent.parent / "shared" / "data" / "real"


def root() -> Path:
    return Path(os.environ.get("MAGCAL_REAL_DATA", DEFAULT_ROOT))


def _csv(path, skip=1, cols=None, delim=","):
    a = np.loadtxt(path, delimiter=delim, skiprows=skip, usecols=cols, ndmin=2)
    return a[np.all(np.isfinite(a), axis=1)]


def _uniform(n, rate_hz):
    return np.arange(n) / float(rate_hz)


def hmc5883l_full_sphere():
    a = _csv(root() / "hmc5883l_sunsided" / "set-2_full-sphere_hmc5883l_mag.csv", cols=(0, 1, 2, 3))
    return a[:, 0], a[:, 1:4] * 100.0  # gauss → µT


def hmc5883l_tilt_sphere():
    a = _csv(root() / "hmc5883l_sunsided" / "set-1_tilt-sphere_hmc5883l_mag.csv", cols=(0, 1, 2, 3))
    return a[:, 0], a[:, 1:4] * 100.0


def qmc5883l_filtered():
    a = _csv(root() / "qmc5883l_tomisuarez" / "filtered_raw_data.csv", skip=3)
    a = a[60 * 50 :]  # the 60 s static lead-in (PROVENANCE.md)
    return _uniform(len(a), 50.0), a


def lsm9ds1_ckexplorer():
    a = _csv(root() / "lsm9ds1_ckexplorer" / "acc_mag_log.csv", cols=(3, 4, 5))
    return _uniform(len(a), 50.0), a * 100.0  # rate not stated: assume 50 Hz


def hmc5843_magcal_example():
    a = _csv(root() / "magcal_ucalgary_example_hmc5843" / "mag.txt", skip=0, delim="\t")
    return _uniform(len(a), 50.0), a * 100.0


def gearvr_mag_data():
    a = _csv(root() / "gearvr_utzinger" / "mag_data.txt", skip=0, delim=" ")
    return _uniform(len(a), 50.0), a


def fxos8700():
    a = _csv(root() / "fxos8700_mwrona" / "mag-readings.txt", skip=0, delim="\t")
    return _uniform(len(a), 10.0), a


def _table(path):
    """(column index by name, float array) of a CSV with a header; blanks and text are NaN."""
    import csv

    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    col = {h: i for i, h in enumerate(rows[0]) if h}

    def num(x):
        try:
            return float(x)
        except ValueError:
            return float("nan")

    return col, np.array([[num(x) for x in r[: len(rows[0])]] for r in rows[1:]])


def _umich_preflight(cols, scale):
    col, a = _table(root() / "icm20948_rm3100_umich_ads" / "preflight" / "data_original.csv")
    t = np.linspace(0.0, float(a[-1, col["unix_time"]] - a[0, col["unix_time"]]), len(a))  # whole-second clock
    return t, a[:, [col[c] for c in cols]] * scale


def umich_preflight_icm():
    return _umich_preflight(("imu_mx", "imu_my", "imu_mz"), 0.15)  # AK09916, 0.15 µT/LSB


def umich_preflight_rm3100():
    return _umich_preflight(("mag_x", "mag_y", "mag_z"), 1 / 75.0)  # PNI RM3100, 75 LSB/µT


def _umich_flight(fname):
    base = root() / "icm20948_rm3100_umich_ads" / "flight"
    t = np.loadtxt(base / "data_ADSflight_times.csv", delimiter=",", ndmin=1)
    return np.linspace(0.0, float(t.max() - t.min()), len(t)), np.loadtxt(base / fname, delimiter=",")


def umich_flight_icm():
    return _umich_flight("data_ADSflight_imu.csv")


def umich_flight_rm3100():
    return _umich_flight("data_ADSflight_pni.csv")


def _betaflight(stem):
    col, a = _table(root() / "qmc5883l_betaflight_pichim" / f"{stem}_calwindow_mag.csv")
    return a[:, col["t_s"]], a[:, [col["mag_x"], col["mag_y"], col["mag_z"]]] / 30.0  # 3000 LSB/G


def estibone_rm3100():
    a = _csv(root() / "mpu9250_rm3100_umich_estibone" / "test0_esti_trunc_rm3100.csv")
    return _uniform(len(a), 50.0), a  # µT; rate not stated


LOADERS = {
    "hmc5883l_full_sphere": hmc5883l_full_sphere,
    "hmc5883l_tilt_sphere": hmc5883l_tilt_sphere,
    "qmc5883l_filtered": qmc5883l_filtered,
    "lsm9ds1_ckexplorer": lsm9ds1_ckexplorer,
    "hmc5843_magcal_example": hmc5843_magcal_example,
    "gearvr_mag_data": gearvr_mag_data,
    "fxos8700": fxos8700,
}

# raw recordings for the raw-injection benchmark (diagnose_raw.py): the seven above plus the
# umich and Betaflight logs and the estibone RM3100; field in µT where the unit is known
RAW_LOADERS = dict(LOADERS)
RAW_LOADERS.update({
    "umich_preflight_icm20948": umich_preflight_icm,
    "umich_preflight_rm3100": umich_preflight_rm3100,
    "umich_flight_icm20948": umich_flight_icm,
    "umich_flight_rm3100": umich_flight_rm3100,
    "betaflight_apex5_tpu_02": lambda: _betaflight("20231014_apex5_mag_on_tpu_02"),
    "betaflight_apex5_tpu_03": lambda: _betaflight("20231014_apex5_mag_on_tpu_03"),
    "betaflight_calcareful": lambda: _betaflight("CalCareful_2282320"),
    "betaflight_caltest1": lambda: _betaflight("calTest1_198_253_-9"),
    "estibone_rm3100": estibone_rm3100,
})
# recordings whose counts have no stated unit: scaled to a 50 µT mean radius (shape kept)
UNKNOWN_UNIT = {"qmc5883l_filtered"}


def available(loaders: dict | None = None) -> dict:
    out = {}
    for name, fn in (LOADERS if loaders is None else loaders).items():
        try:
            out[name] = fn()
        except (OSError, ValueError):
            continue
    return out


def raw_in_ut(quick: bool = False, max_n: int = 6000) -> dict:
    """The raw recordings for injection benches (bench/locate_*.py): each thinned to at most
    about ``max_n`` samples, time from 0, counts of no stated unit scaled to a 50 µT radius;
    ``quick``: the first four by name."""
    out = {}
    for name, (t, m) in sorted(available(RAW_LOADERS).items())[: 4 if quick else None]:
        k = max(1, len(m) // max_n)
        t, m = np.asarray(t, float)[::k], np.asarray(m, float)[::k]
        if name in UNKNOWN_UNIT:
            m = m * 50.0 / np.median(np.linalg.norm(m - m.mean(0), axis=1))
        out[name] = (t - t[0], m)
    return out
