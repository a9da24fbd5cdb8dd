"""Every file under ../shared/data/real: ``magcal diagnose`` (default options) against
``magcal fit --model auto`` on held-out time blocks.

    python3 bench/diagnose_vs_fit.py [--folds 5] [--json]

Each file is read as the commands read it (``load_series``), with no options where the file
needs none and with the options its PROVENANCE.md names otherwise (a headerless log, a table
with two magnetometers). ``diagnose`` runs with its defaults (channels that follow the
orientation or the reading left out); then magcal.diagnose.versus_fit refits both
procedures without each of 5 contiguous blocks and judges them on it (the relative radial
error of the calibrated field, in µT at the recording's field). Files no command reads (binary
flight logs: issue of the log readers) and files that are not a rotation (a still board, static
survey shots) are listed with the reason.

Data: ../shared/data/real relative to the repository (override with MAGCAL_REAL_DATA).
"""

from __future__ import annotations

import json
import os
import sys
import time
import warnings
from pathlib import Path

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # one BLAS thread, set before numpy loads
    os.environ.setdefault(_name, "1")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from magcal.app.load import load_series  # noqa: E402
from magcal.core.errors import MagcalError  # noqa: E402
from magcal.diagnose import diagnose  # noqa: E402
from magcal.diagnose.versus_fit import heldout_versus_fit  # noqa: E402
from magcal.recordings.table import TableFormat  # noqa: E402

ROOT = Path(os.environ.get("MAGCAL_REAL_DATA", HERE.parent.parent / "shared" / "data" / "real"))
PESBOARD = TableFormat(columns=("7", "8", "9"), unit="gauss", time="10", time_unit="ms")  # the README's example
# (file, table options or None, why these options)
FILES = [
    ("ardupilot_solo_log171/log171.bin", None, ""),
    ("fluxgate_magnav_flt1002/Flt1002_1002.02.txt", TableFormat(columns=("2", "3", "4"), unit="0.001", time="1"),
     "headerless: flux_x,y,z in nT, time in s (PROVENANCE.md)"),
    ("fxos8700_mwrona/mag-readings.txt", None, ""),
    ("gearvr_utzinger/Officeacc.txt", None, ""),
    ("gearvr_utzinger/Officemag.txt", None, ""),
    ("gearvr_utzinger/mag_data.txt", None, ""),
    ("hmc5883l_sunsided/set-1_tilt-sphere_hmc5883l_mag.csv", None, ""),
    ("hmc5883l_sunsided/set-2_full-sphere_hmc5883l_mag.csv", None, ""),
    ("hmc5883l_sunsided/set-2_unmoved-with-x-pointing-forward-10min_hmc5883l_mag.csv", None, ""),
    ("icm20948_rm3100_umich_ads/flight/data_ADSflight_imu.csv", None, ""),
    ("icm20948_rm3100_umich_ads/flight/data_ADSflight_pni.csv", None, ""),
    ("icm20948_rm3100_umich_ads/preflight/data_original.csv", TableFormat(columns=("imu_mx", "imu_my", "imu_mz"), unit="0.15"),
     "two magnetometers: the ICM-20948's (0.15 µT/LSB)"),
    ("icm20948_rm3100_umich_ads/preflight/data_original.csv", TableFormat(columns=("mag_x", "mag_y", "mag_z"), unit=str(1 / 75)),
     "two magnetometers: the RM3100's (75 LSB/µT)"),
    ("icm20948_rm3100_umich_ads/preflight/data_original_imu.csv", None, ""),
    ("icm20948_rm3100_umich_ads/preflight/data_original_pni.csv", None, ""),
    ("lsm9ds1_ckexplorer/acc_mag_log.csv", None, ""),
    ("lsm9ds1_pesboard_zhaw/putty_00.log", PESBOARD, "headerless: the README's example options"),
    ("lsm9ds1_pesboard_zhaw/putty_01.log", PESBOARD, "headerless: the README's example options"),
    ("lsm9ds1_pesboard_zhaw/putty_05.log", PESBOARD, "headerless: the README's example options"),
    ("magcal_ucalgary_example_hmc5843/mag.txt", None, ""),
    ("mpu9250_rm3100_umich_estibone/test0_esti_trunc_rm3100.csv", None, ""),
    ("mpu9250_rm3100_umich_estibone/test1_esti.csv", None, ""),
    ("px4_cube_uavcan_esc/esc_status_log.ulg", None, ""),
    ("qmc5883l_betaflight_pichim/20231014_apex5_mag_on_tpu_02_calwindow_mag.csv", None, ""),
    ("qmc5883l_betaflight_pichim/20231014_apex5_mag_on_tpu_03_calwindow_mag.csv", None, ""),
    ("qmc5883l_betaflight_pichim/CalCareful_2282320_calwindow_mag.csv", None, ""),
    ("qmc5883l_betaflight_pichim/calTest1_198_253_-9_calwindow_mag.csv", None, ""),
    ("qmc5883l_tomisuarez/filtered_raw_data.csv", None, ""),
    ("qmc5883l_tomisuarez/noisy_raw_data.csv", None, ""),
    ("sap6_cave_survey_furbrain/sap6_all_devices_shots.csv", None, ""),
]


def one(path: Path, fmt, folds: int) -> dict:
    t0 = time.process_time()
    try:
        series = load_series(path, fmt)
        d = diagnose(series)
    except MagcalError as exc:
        return {"status": "not diagnosed", "why": str(exc).split(": ", 1)[-1][:140]}
    v = heldout_versus_fit(d, folds)
    if v is None:
        return {"status": "fit finds no model"}
    return {"status": "ok", "samples": d.n_samples, "model": d.to_dict()["final"]["model"], "from": d.to_dict()["final"]["from"],
            "diagnose_heldout_ut": v.diagnose_rms_ut, "fit_heldout_ut": v.fit_rms_ut, "never_worse": v.never_worse,
            "seconds_cpu": time.process_time() - t0}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    warnings.filterwarnings("ignore")
    folds = int(argv[argv.index("--folds") + 1]) if "--folds" in argv else 5
    rows = []
    for rel, fmt, why in FILES:
        r = {"file": rel, "options": why, **one(ROOT / rel, fmt, folds)}
        rows.append(r)
        if "--json" not in argv:
            if r["status"] == "ok":
                print(f"{rel:<80} {r['model']:<22} {r['from']:<9} {r['diagnose_heldout_ut']:8.3f} {r['fit_heldout_ut']:8.3f}  "
                      f"{'ok' if r['never_worse'] else 'WORSE'}  {why}", flush=True)
            else:
                print(f"{rel:<80} {r['status']}: {r.get('why', '')}", flush=True)
    ok = [r for r in rows if r["status"] == "ok"]
    print(f"never worse on {sum(r['never_worse'] for r in ok)} of {len(ok)} diagnosed files; {len(rows) - len(ok)} not diagnosed")
    if "--json" in argv:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
