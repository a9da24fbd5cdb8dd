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


LOADERS = {
    "hmc5883l_full_sphere": hmc5883l_full_sphere,
    "hmc5883l_tilt_sphere": hmc5883l_tilt_sphere,
    "qmc5883l_filtered": qmc5883l_filtered,
    "lsm9ds1_ckexplorer": lsm9ds1_ckexplorer,
    "hmc5843_magcal_example": hmc5843_magcal_example,
    "gearvr_mag_data": gearvr_mag_data,
    "fxos8700": fxos8700,
}


def available() -> dict:
    out = {}
    for name, fn in LOADERS.items():
        try:
            out[name] = fn()
        except (OSError, ValueError):
            continue
    return out
