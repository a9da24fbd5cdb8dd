"""The peer of ``bench/tracking.py``: PJRC MotionCal's own calibration core, driven offline.

MotionCal (github.com/PaulStoffregen/MotionCal) is a GUI; its calibration core (``rawdata.c``,
``magcal.c``, ``matrix.c``, ``quality.c``, ``mahony.c``) is plain C. A small driver links those
files unmodified and feeds them a recording the way the GUI does (14 ms timer, at most 256 bytes
of "Raw:" lines per tick, a quality refresh per repaint, integer counts of 0.1 µT). It is not
part of magcal and is not shipped here; this module runs it and keeps its figures.

Driver: the path in ``MAGCAL_MOTIONCAL_DRIVER``. ``DRIVER FILE.csv --json`` (CSV header
``t,mx,my,mz`` in µT) prints the calibration after the last sample as JSON
(``{"calibration": {"offset_ut": V, "soft_iron": invW, ...}}``, calibrated = invW·(m − V)); with
``MC_TRACE=1`` it also prints one line ``T k V0 V1 V2 W00 W01 W02 W11 W12 W22 B valid`` each
time the calibration in force changes (after sample k, 0-based). ``MC_SEED`` seeds its
``random()`` (it picks at random which of the two closest buffered points to drop, so its
figures vary with the seed: always compare medians over seeds).

Figures the driver produced are kept in ``bench/results/motioncal_figures.json`` keyed by
recording, cell, seed and a digest of the samples fed, so the tables can be reprinted without
the driver (and say so) and a changed loader is never matched with stale figures.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
DRIVER_ENV = "MAGCAL_MOTIONCAL_DRIVER"
CACHE = os.path.join(HERE, "results", "motioncal_figures.json")
HOW_TO_BUILD = (
    "MotionCal's figures need its calibration core. Build a driver from PJRC MotionCal's\n"
    "unmodified rawdata.c, magcal.c, matrix.c, quality.c and mahony.c (commit c24740c) that reads\n"
    "a t,mx,my,mz CSV (µT), feeds it as the GUI does and prints the final calibration as JSON\n"
    "(and, with MC_TRACE=1, one 'T k V… invW… B valid' line per change), then set\n"
    f"{DRIVER_ENV}=/path/to/driver. Without it only the figures already in\n"
    "bench/results/motioncal_figures.json can be used."
)


class NoDriver(RuntimeError):
    pass


def digest(t, m) -> str:
    """Short digest of exactly what is fed to the driver (as written to its CSV)."""
    return hashlib.sha256(_csv(t, m).encode()).hexdigest()[:16]


def _csv(t, m) -> str:
    rows = [f"{a:.4f},{x:.1f},{y:.1f},{z:.1f}" for a, (x, y, z) in zip(t, m)]
    return "t,mx,my,mz\n" + "\n".join(rows) + "\n"


def _run(t, m, seed: int, trace: bool) -> str:
    path = os.environ.get(DRIVER_ENV)
    if not path or not os.access(path, os.X_OK):
        raise NoDriver(HOW_TO_BUILD)
    with tempfile.NamedTemporaryFile("w", suffix=".csv", delete=False) as f:
        f.write(_csv(t, m))
    env = dict(os.environ, MC_SEED=str(seed), MC_TRACE="1" if trace else "0")
    try:
        out = subprocess.run([path, f.name, "--json"], env=env, capture_output=True, text=True, check=True)
    finally:
        os.unlink(f.name)
    return out.stdout


def final(t, m, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(V, invW) MotionCal would send after the last sample."""
    line = [s for s in _run(t, m, seed, trace=False).splitlines() if s.startswith("{")][-1]
    c = json.loads(line)["calibration"]
    return np.array(c["offset_ut"]), np.array(c["soft_iron"])


def trace(t, m, seed: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """[(k, V, invW)]: each calibration MotionCal put in force, after sample k."""
    out = []
    for s in _run(t, m, seed, trace=True).splitlines():
        if not s.startswith("T "):
            continue
        f = s.split()
        v = np.array([float(x) for x in f[2:12]])
        W = np.array([[v[3], v[4], v[5]], [v[4], v[6], v[7]], [v[5], v[7], v[8]]])
        out.append((int(f[1]), v[:3], W))
    if not out:
        raise NoDriver(f"the driver in {DRIVER_ENV} printed no trace lines (MC_TRACE=1)\n" + HOW_TO_BUILD)
    return out


class Figures:
    """The peer's figures by key, read from and written back to ``CACHE``."""

    def __init__(self, path: str = CACHE):
        self.path = path
        self.data = {}
        if os.path.exists(path):
            with open(path) as f:
                self.data = json.load(f)
        self.dirty = False

    def get(self, key: str, compute):
        if key not in self.data:
            self.data[key] = compute()
            self.dirty = True
        return self.data[key]

    def save(self) -> None:
        if self.dirty:
            os.makedirs(os.path.dirname(self.path), exist_ok=True)
            tmp = self.path + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.data, f, indent=0, sort_keys=True)
            os.replace(tmp, self.path)
            self.dirty = False
