"""Does ``fit --model auto`` choose a model that generalises? Judged forward in time.

    MAGCAL_REAL_DATA=… python bench/model_choice.py [--splits 0.3,0.5,0.7] [--sealed] [--only NAME]

Every real recording this bench can load (the sixteen of ``real_recordings.RAW_LOADERS``, the
LSM9DS1 PES-board takes, each compass of the ArduPilot and PX4 logs, the real excerpts in
tests/data and the public recordings kept there whole, ``_public``) is split in time: ``fit``
sees the part before the split, the part after is judged by the held-out spread std/mean of
|calibrated field| (%). Three fits of the same part:

* auto      — ``fit_calibration(train, model="auto")``, what ``magcal fit`` does;
* sphere    — a plain sphere: ``model="sphere"`` with no coverage gate;
* ellipsoid — a plain 9-parameter ellipsoid: ``model="ellipsoid"`` with no coverage or shape
              gate and no direction balance (outlier removal kept).

Printed per cell: the three spreads, auto's model and the ratio auto ÷ min(sphere, ellipsoid)
(target ≤ 1.02 everywhere); a refusal of auto is shown as such. The recordings listed in
docs/sealed.md are left out unless ``--sealed`` is given, which prints only them.
"""

from __future__ import annotations

import argparse
import os
import sys
import tomllib
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import real_recordings as rr  # noqa: E402

from magcal.fit import fit_calibration  # noqa: E402

SPLITS = (0.3, 0.5, 0.7)
TESTS_DATA = os.path.join(HERE, "..", "tests", "data")
# the public recordings kept whole in tests/data: named, with their part and unit, only there
with open(os.path.join(TESTS_DATA, "public_recordings.toml"), "rb") as _f:
    PUBLIC = tuple(tomllib.load(_f)["recording"])
SEALED = ("betaflight_apex5_tpu_03", "umich_preflight_icm20948", "ardupilot_log171 compass 1",
          *(r["name"] for r in PUBLIC if r["sealed"]))
UNGATED = float("inf")


def _pesboard(name):
    a = np.genfromtxt(rr.root() / "lsm9ds1_pesboard_zhaw" / name, delimiter=",")
    a = a[np.all(np.isfinite(a[:, 6:10]), axis=1)]
    return a[:, 9] / 1000.0, a[:, 6:9] * 100.0  # ms, gauss → µT


def _flight_logs() -> dict:
    from magcal.recordings.logs import read_log, select

    out = {}
    for stem, path in (("ardupilot_log171", "ardupilot_solo_log171/log171.bin"),
                       ("px4_cube_uavcan_esc", "px4_cube_uavcan_esc/esc_status_log.ulg")):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                log = read_log(str(rr.root() / path))
                for mag in log.mags:
                    s = select(log, mag.index).series
                    out[f"{stem} compass {mag.index}"] = (s.t_s, s.field_ut[s.valid])
        except Exception:  # a log this machine cannot read is left out, not fatal
            continue
    return out


def _tests_data() -> dict:
    out = {}
    for name, cols, scale in (("lsm9ds1_ckexplorer_every4th.csv", (0, 1, 2), 1.0),
                              ("qmc5883l_tomisuarez_every5th_counts.csv", (0, 1, 2), 1.0),
                              ("hmc5883l_sunsided_tilt_sphere_counts.csv", (1, 2, 3), 100 / 1090)):
        try:
            a = np.loadtxt(os.path.join(TESTS_DATA, name), delimiter=",", skiprows=1, usecols=cols, ndmin=2)
        except (OSError, ValueError):
            continue
        out[f"tests/data {name}"] = (np.arange(len(a)), a * scale)
    return out


def _public() -> dict:
    """name → (t_s, µT) of the public recordings kept whole in tests/data that are no copy of a
    recording in MAGCAL_REAL_DATA (``PUBLIC``, tests/data/public_recordings.toml; the sealed ones
    among them are in ``SEALED``)."""
    out = {}
    for r in PUBLIC:
        try:
            a = np.loadtxt(os.path.join(TESTS_DATA, r["file"]), delimiter=",", skiprows=1, ndmin=2)
        except (OSError, ValueError):
            continue
        out[r["name"]] = (a[:, 0], a[:, 1:4] * np.asarray(r["ut_per_count"], float))
    return out


def recordings() -> dict[str, np.ndarray]:
    """name → (n, 3) field in time order, finite rows only."""
    recs = {k: m for k, (t, m) in rr.available(rr.RAW_LOADERS).items()}
    for f in ("putty_00.log", "putty_05.log"):
        try:
            recs[f"lsm9ds1_pesboard {f}"] = _pesboard(f)[1]
        except (OSError, ValueError):
            pass
    recs.update({k: m for k, (t, m) in _flight_logs().items()})
    recs.update({k: m for k, (t, m) in _tests_data().items()})
    recs.update({k: m for k, (t, m) in _public().items()})
    return {k: np.asarray(m, float)[np.all(np.isfinite(m), axis=1)] for k, m in recs.items()}


def spread_pct(m, cal) -> float:
    h = np.linalg.norm((m - cal.offset_ut) @ np.asarray(cal.soft_iron).T, axis=1)
    return float(100 * np.std(h) / np.mean(h))


def cell(train, test) -> dict:
    auto = fit_calibration(train, model="auto")
    sph = fit_calibration(train, model="sphere", max_condition=UNGATED)
    ell = fit_calibration(train, model="ellipsoid", balance="none", max_condition=UNGATED,
                          max_ellipsoid_condition=UNGATED, max_shape_sigma=UNGATED)
    out = {"auto": spread_pct(test, auto.calibration) if auto else float("nan"),
           "model": auto.model if auto else f"refused ({auto.reason})",
           "sphere": spread_pct(test, sph.calibration) if sph else float("nan"),
           "ellipsoid": spread_pct(test, ell.calibration) if ell and ell.model == "ellipsoid" else float("nan")}
    plain = [v for v in (out["sphere"], out["ellipsoid"]) if np.isfinite(v)]
    out["best"] = min(plain) if plain else float("nan")  # neither plain fit possible: nothing to compare
    out["ratio"] = out["auto"] / out["best"]
    return out


def run(recs: dict, splits) -> list[float]:
    print("| recording | n | split | auto % | auto's model | sphere % | ellipsoid % | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    ratios = []
    for name, m in recs.items():
        for f in splits:
            k = int(len(m) * f)
            c = cell(m[:k], m[k:])
            ratios.append(c["ratio"])
            print(f"| {name} | {len(m)} | {f:.0%} | {c['auto']:.3f} | {c['model']} | {c['sphere']:.3f} | "
                  f"{c['ellipsoid']:.3f} | {c['ratio']:.3f} |", flush=True)
    r = np.array(ratios)
    ok = r[np.isfinite(r)]
    if not len(ok):  # e.g. a take still until its last tenth: every training part refused
        print(f"\n{len(r)} cells: none scored, auto refused in {len(r)}")
        return ratios
    print(f"\n{len(r)} cells: worst ratio {ok.max():.3f}, geometric mean {np.exp(np.mean(np.log(ok))):.3f}, "
          f"above 1.02 in {int(np.sum(ok > 1.02))}, auto refused in {int(np.sum(~np.isfinite(r)))}")
    return ratios


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--splits", default=",".join(str(f) for f in SPLITS))
    ap.add_argument("--sealed", action="store_true", help="only the sealed recordings of docs/sealed.md")
    ap.add_argument("--only", action="append", help="only this recording (repeatable)")
    a = ap.parse_args(argv)
    recs = {k: v for k, v in recordings().items()
            if (k in SEALED) == a.sealed and (not a.only or k in a.only)}
    run(recs, tuple(float(x) for x in a.splits.split(",")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
