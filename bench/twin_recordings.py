"""Every real recording under ../shared/data/real with at least 1000 magnetometer samples, as
Series in µT (the sensor twin benchmarks). Columns, units and rates as each folder's
PROVENANCE.md gives them; where it gives no rate, the one assumed is named in ``RATE_NOTE``.

Each entry: name → (loader, note). A loader returns (Series, fixed) where ``fixed`` is a
calibration to use instead of fitting one (a still recording, which cannot determine one), or
None. Data root: MAGCAL_REAL_DATA, else ../shared/data/real beside the repository.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from magcal.core.series import Series
from magcal.fit import fit_calibration as fit

HERE = Path(__file__).resolve().parent
MIN_SAMPLES = 1000


def root() -> Path:
    return Path(os.environ.get("MAGCAL_REAL_DATA", HERE.parent.parent / "shared" / "data" / "real"))


def _csv(rel, cols, skip=1, delim=","):
    a = np.genfromtxt(root() / rel, delimiter=delim, skip_header=skip, usecols=cols)
    return a[np.all(np.isfinite(a), axis=1)]


def _series(m, rate_hz=None, t=None, channels=None):
    t = np.arange(len(m)) / rate_hz if t is None else t
    return Series(t_s=t, field_ut=m, channels=channels or {})


def _distinct(m):
    """Rows where the reading changed (a logger faster than the sensor repeats samples)."""
    keep = np.concatenate([[True], np.any(np.diff(m, axis=0) != 0, axis=1)])
    return keep


def hmc_full():
    a = _csv("hmc5883l_sunsided/set-2_full-sphere_hmc5883l_mag.csv", (0, 1, 2, 3))
    return _series(a[:, 1:4] * 100.0, t=a[:, 0]), None


def hmc_tilt():
    a = _csv("hmc5883l_sunsided/set-1_tilt-sphere_hmc5883l_mag.csv", (0, 1, 2, 3))
    return _series(a[:, 1:4] * 100.0, t=a[:, 0]), None


def hmc_still():
    """The 10-minute still take of set 2: its calibration is the full-sphere take's (same
    board, same session), since a still board determines none."""
    a = _csv("hmc5883l_sunsided/set-2_unmoved-with-x-pointing-forward-10min_hmc5883l_mag.csv", (0, 1, 2, 3))
    full, _ = hmc_full()
    return _series(a[:, 1:4] * 100.0, t=a[:, 0]), fit(full.field_ut, model="ellipsoid").calibration


def lsm_ck():
    return _series(_csv("lsm9ds1_ckexplorer/acc_mag_log.csv", (3, 4, 5)) * 100.0, 50.0), None


def gearvr(name):
    return lambda: (_series(_csv(f"gearvr_utzinger/{name}", (0, 1, 2), 0, None), 50.0), None)


def qmc_tomi(name):
    def load():
        a = _csv(f"qmc5883l_tomisuarez/{name}", (0, 1, 2), 3)
        return _series(a * (100.0 / 3000.0), 50.0), None  # 3000 LSB/G (±8 G range): counts → µT
    return load


def pesboard(name):
    def load():
        a = _csv(f"lsm9ds1_pesboard_zhaw/{name}", (6, 7, 8, 9), 0)
        return _series(a[:, 0:3] * 100.0, t=a[:, 3] / 1000.0), None
    return load


def hmc5843():
    return _series(_csv("magcal_ucalgary_example_hmc5843/mag.txt", (0, 1, 2), 0, "\t") * 100.0, 50.0), None


def betaflight(name):
    def load():
        a = _csv(f"qmc5883l_betaflight_pichim/{name}", (0, 1, 2, 3, 10, 11))
        m = a[:, 1:4] * (100.0 / 3000.0)  # QMC5883L counts at ±8 G
        return _series(m, t=a[:, 0], channels={"vbat_v": a[:, 4], "current_a": a[:, 5]}), None
    return load


def umich_ads(part, which):
    def load():
        if part == "preflight":
            a = _csv("icm20948_rm3100_umich_ads/preflight/data_original.csv", (8, 9, 10, 11, 12, 13, 14))
            m = a[:, 0:3] * 0.15 if which == "imu" else a[:, 4:7] / 75.0
            return _series(m, 10.0, channels={"temp_c": a[:, 3]}), None  # ~10 Hz; whole-second stamps
        m = _csv(f"icm20948_rm3100_umich_ads/flight/data_ADSflight_{which}.csv", (0, 1, 2), 0)
        t = np.genfromtxt(root() / "icm20948_rm3100_umich_ads/flight/data_ADSflight_times.csv")[: len(m)]
        return _series(m[: len(t)], t=t - t[0]), None
    return load


def estibone(col):
    def load():
        if col == "test0":
            return _series(_csv("mpu9250_rm3100_umich_estibone/test0_esti_trunc_rm3100.csv", (0, 1, 2)), 100.0), None
        cols = (14, 15, 16) if col == "ak8963" else (88, 89, 90)
        a = _csv("mpu9250_rm3100_umich_estibone/test1_esti.csv", cols)
        t = np.arange(len(a)) / 200.0
        keep = _distinct(a)
        return _series(a[keep], t=t[keep]), None
    return load


def fluxgate():
    a = _csv("fluxgate_magnav_flt1002/Flt1002_1002.02.txt", (0, 1, 2, 3), 0, "\t")
    return _series(a[:, 1:4] / 1000.0, t=a[:, 0] - a[0, 0]), None  # nT → µT


# -- ArduPilot DataFlash (.bin): self-describing FMT messages -------------------------------
_TYPES = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "n": "4s", "N": "16s",
          "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B", "q": "q", "Q": "Q", "a": "64s"}
_SCALE = {"c": 0.01, "C": 0.01, "e": 0.01, "E": 0.01}


def dataflash(path, wanted):
    """{name: {column: array}} for the message names in ``wanted``."""
    data = (root() / path).read_bytes()
    fmts = {128: ("FMT", "BBnNZ", ["Type", "Length", "Name", "Format", "Columns"], 89)}
    out = {w: [] for w in wanted}
    i = 0
    while i + 3 <= len(data):
        if data[i] != 0xA3 or data[i + 1] != 0x95:
            i += 1
            continue
        mid = data[i + 2]
        if mid not in fmts:
            i += 1
            continue
        name, fmt, cols, length = fmts[mid]
        body = data[i + 3 : i + length]
        if len(body) < length - 3:
            break
        vals = struct.unpack("<" + "".join(_TYPES[c] for c in fmt), body)
        if name == "FMT":
            t, ln, nm, f, c = vals
            fmts[t] = (nm.rstrip(b"\0").decode(), f.rstrip(b"\0").decode(), c.rstrip(b"\0").decode().split(","), ln)
        elif name in out:
            out[name].append([v * _SCALE.get(k, 1.0) if not isinstance(v, bytes) else 0 for v, k in zip(vals, fmt)])
        i += length
    return {n: dict(zip(next(f[2] for f in fmts.values() if f[0] == n), np.array(rows, float).T)) for n, rows in out.items() if rows}


def ardupilot(msg):
    def load():
        logs = dataflash("ardupilot_solo_log171/log171.bin", ("MAG", "MAG2", "MAG3", "CURR"))
        g = logs[msg]
        t = g["TimeMS"] * 1e-3
        m = np.column_stack([g["MagX"], g["MagY"], g["MagZ"]]) * 0.1  # mGauss → µT
        cur = logs["CURR"]
        chans = {"current_a": np.interp(t, cur["TimeMS"] * 1e-3, cur["Curr"])}
        return _series(m, t=t - t[0], channels=chans), None
    return load


RECORDINGS = {
    "hmc5883l set-2 full sphere": hmc_full,
    "hmc5883l set-1 tilt sphere": hmc_tilt,
    "hmc5883l set-2 still 10 min": hmc_still,
    "lsm9ds1 ckexplorer": lsm_ck,
    "gearvr mag_data": gearvr("mag_data.txt"),
    "gearvr Officemag": gearvr("Officemag.txt"),
    "qmc5883l tomisuarez filtered": qmc_tomi("filtered_raw_data.csv"),
    "qmc5883l tomisuarez noisy": qmc_tomi("noisy_raw_data.csv"),
    "lsm9ds1 pesboard putty_00": pesboard("putty_00.log"),
    "lsm9ds1 pesboard putty_01": pesboard("putty_01.log"),
    "lsm9ds1 pesboard putty_05": pesboard("putty_05.log"),
    "hmc5843 ucalgary": hmc5843,
    "qmc5883l betaflight tpu_02": betaflight("20231014_apex5_mag_on_tpu_02_calwindow_mag.csv"),
    "qmc5883l betaflight tpu_03": betaflight("20231014_apex5_mag_on_tpu_03_calwindow_mag.csv"),
    "qmc5883l betaflight CalCareful": betaflight("CalCareful_2282320_calwindow_mag.csv"),
    "qmc5883l betaflight calTest1": betaflight("calTest1_198_253_-9_calwindow_mag.csv"),
    "icm20948 umich preflight": umich_ads("preflight", "imu"),
    "rm3100 umich preflight": umich_ads("preflight", "pni"),
    "icm20948 umich flight": umich_ads("flight", "imu"),
    "rm3100 umich flight": umich_ads("flight", "pni"),
    "rm3100 estibone test0": estibone("test0"),
    "ak8963 estibone test1": estibone("ak8963"),
    "rm3100 estibone test1": estibone("rm3100"),
    "ardupilot solo MAG (external HMC5883)": ardupilot("MAG"),
    "ardupilot solo MAG2 (LSM303D)": ardupilot("MAG2"),
    "ardupilot solo MAG3 (HMC, raw)": ardupilot("MAG3"),
    "fluxgate magnav flt1002": fluxgate,
}
RATE_NOTE = ("rates assumed where the files carry no time: 50 Hz (lsm9ds1 ckexplorer, gearvr, qmc5883l tomisuarez, "
             "hmc5843), 100 Hz (estibone test0), 200 Hz rows (estibone test1, repeated rows dropped), 10 Hz (umich preflight)")


def load(name):
    series, fixed = RECORDINGS[name]()
    return series, fixed
