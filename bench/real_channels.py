"""``diagnose`` on real recordings that log real auxiliary channels, as a user would run it.

    python3 bench/real_channels.py [--json]

The injected-effect benchmark (diagnose_bench.py) knows the truth because it puts it there;
these recordings carry their own channels, so what is printed is what diagnose says about each,
to be read against what is known of the hardware (see each folder's PROVENANCE.md):

* icm20948_rm3100_umich_ads, preflight: a hand rotation outdoors before a balloon flight, an
  ICM-20948 (its AK09916 magnetometer, 0.15 µT/LSB) and a PNI RM3100 (75 LSB/µT) on one board,
  logged together at about 10 Hz with the ICM die temperature (`imu_T`, 12 → 8 °C), ambient
  temperature, pressure and humidity. The log's clock has whole seconds only, so the samples are
  placed on a uniform grid over the logged span (128 s).
* the same board's 1.5 h balloon flight (53 322 samples of each sensor, µT, no channels).
* qmc5883l_betaflight_pichim: the calibration windows of four Betaflight flight-controller logs
  (QMC5883L at ±8 G, 3000 LSB/G → 1/30 µT per count), with the controller's current sensor
  (0–3.2 A from the electronics; the motors were stopped), battery voltage and throttle.

Data: ../shared/data/real relative to the repository (override with MAGCAL_REAL_DATA). Neither
source states a licence, so nothing of them is copied into the repository.
"""

from __future__ import annotations

import csv
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from magcal.core.series import Series  # noqa: E402
from magcal.diagnose import diagnose  # noqa: E402

ROOT = Path(os.environ.get("MAGCAL_REAL_DATA", HERE.parent.parent / "shared" / "data" / "real"))


def _table(path: Path) -> tuple[dict, np.ndarray]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    col = {h: i for i, h in enumerate(rows[0]) if h}

    def num(x: str) -> float:
        try:
            return float(x)
        except ValueError:
            return float("nan")

    return col, np.array([[num(x) for x in r[: len(rows[0])]] for r in rows[1:]])


def umich_preflight():
    col, a = _table(ROOT / "icm20948_rm3100_umich_ads" / "preflight" / "data_original.csv")
    unix = a[:, col["unix_time"]]
    t = np.linspace(0.0, float(unix[-1] - unix[0]), len(a))
    chans = {"temp_c": a[:, col["imu_T"]], "enviro_t": a[:, col["enviro_t"]],
             "enviro_p": a[:, col["enviro_p"]], "enviro_h": a[:, col["enviro_h"]]}
    yield "umich preflight, ICM-20948 (AK09916)", Series(t_s=t, field_ut=a[:, [col["imu_mx"], col["imu_my"], col["imu_mz"]]] * 0.15, channels=chans)
    yield "umich preflight, PNI RM3100", Series(t_s=t, field_ut=a[:, [col["mag_x"], col["mag_y"], col["mag_z"]]] / 75.0, channels=chans)


def umich_flight():
    """The 1.5 h balloon flight of the same board (µT files; no channels in them). The unix
    times are fractional here and only used for their span."""
    base = ROOT / "icm20948_rm3100_umich_ads" / "flight"
    t = np.loadtxt(base / "data_ADSflight_times.csv", delimiter=",", ndmin=1)
    t = np.linspace(0.0, float(t.max() - t.min()), len(t))
    for label, fname in (("ICM-20948 (AK09916)", "data_ADSflight_imu.csv"), ("PNI RM3100", "data_ADSflight_pni.csv")):
        yield f"umich flight, {label}", Series(t_s=t, field_ut=np.loadtxt(base / fname, delimiter=","))


def betaflight():
    for path in sorted((ROOT / "qmc5883l_betaflight_pichim").glob("*_calwindow_mag.csv")):
        col, a = _table(path)
        chans = {"current_a": a[:, col["current_A"]], "vbat_v": a[:, col["vbat_V"]], "rc_throttle": a[:, col["rc_throttle"]]}
        m = a[:, [col["mag_x"], col["mag_y"], col["mag_z"]]] / 30.0
        yield f"betaflight {path.name.replace('_calwindow_mag.csv', '')}", Series(t_s=a[:, col["t_s"]], field_ut=m, channels=chans)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    warnings.filterwarnings("ignore")
    out = []
    for source in (umich_preflight, umich_flight, betaflight):
        try:
            cases = list(source())
        except OSError as e:
            print(f"{source.__name__}: not available ({e})")
            continue
        for label, series in cases:
            d = diagnose(series).to_dict()
            out.append({"recording": label, **d})
            if "--json" in argv:
                continue
            b, f = d["baseline"], d["final"]
            print(f"\n== {label}: {d['n_samples']} samples, noise {d['noise_ut']:.3f} µT; held-out RMS "
                  f"{b['heldout_rms_ut']:.3f} → {f['heldout_rms_ut']:.3f} µT ({f['model']})")
            for k in d["findings"]:
                print(f"   finding {k['effect']}: {k['summary']}")
            for k in d["limits"]:
                print(f"   limit   {k['effect']}: {k['summary']}")
            if not d["findings"] and not d["limits"]:
                print("   nothing found, nothing left untested")
    if "--json" in argv:
        print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
