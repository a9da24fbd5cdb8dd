"""ArduPilot 4.x conventions on a synthetic DataFlash log written the way the firmware writes one.

From ArduPilot's source (libraries/AP_Compass): the calibration parameters (COMPASS_OFS, DIA,
ODI, MOT, SCALE, EXTERNAL, DEV_ID …) belong to a *slot*; the MAG message is written per *priority*
(``Compass::Write_Compass_instance(time_us, i)`` logs ``get_field(i)``, and ``get_field`` reads
``_get_state(Priority(i))``); priority i is the device whose id is COMPASS_PRIO(i+1)_ID, and its
slot the one whose COMPASS_DEV_ID holds that id (``Compass::_get_state_id``). The 4.x MAG message
is ``QBhhhhhhhhhBI`` — TimeUS, I, MagX/Y/Z, OfsX/Y/Z, MOX/Y/Z, Health, S (S the compass's last
update, µs on the 32-bit clock). ``AP_Compass_Backend::correct_field`` is re-written here:
corrected = M·(s·(raw + OFS)) + MOT·x.

The flight: a slow turn with tilt at a known place and date, three compasses whose priority order
is not their slot order, each logged through its own slot's parameters.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from dataflash_writer import ap4_writer
from logs_extra import need

LAT, LON, ALT_M = 47.397, 8.545, 488.0  # near Zurich
GPS_WEEK, GPS_MS = 2300, 302_400_000  # 2024-02-07
RATE_HZ, SECONDS = 10.0, 150.0
#: slot → (device id, external, OFS mG, DIA, ODI); priorities list devices 0x…09 first
SLOTS = {
    0: (590114, 0, (-120.0, 85.0, 240.0), (0.98, 1.03, 1.01), (0.01, -0.02, 0.005)),   # internal, slot 1
    1: (97539, 1, (35.0, -60.0, 18.0), (1.01, 0.99, 1.02), (-0.004, 0.008, 0.012)),    # external, slot 2
    2: (263178, 0, (200.0, 10.0, -150.0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)),           # internal, slot 3
}
PRIORITY = (97539, 590114, 263178)  # MAG[0] is slot 2's device, MAG[1] slot 1's
TRUE_OFFSET_UT = {0: (12.0, -8.5, 24.0), 1: (-3.5, 6.0, 2.0), 2: (-20.0, -1.0, 15.0)}  # raw = field + this


def _need():
    need("pymavlink", "pygeomag")


def ap_correct(raw_mg, ofs, dia, odi):
    m = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    return (raw_mg + np.asarray(ofs)) @ m.T


def _attitude(t):
    roll = np.radians(25.0) * np.sin(2 * np.pi * t / 37.0)
    pitch = np.radians(20.0) * np.sin(2 * np.pi * t / 23.0 + 0.7)
    yaw = np.radians(360.0 * t / 50.0) % (2 * np.pi)
    return roll, pitch, yaw


def _body_field_mg(t):
    from pygeomag import GeoMag

    r = GeoMag(base_year=2020).calculate(glat=LAT, glon=LON, alt=ALT_M / 1000.0, time=2024.1)
    ned_mg = np.array([r.x, r.y, r.z]) / 100.0  # nT → mG
    roll, pitch, yaw = _attitude(t)
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    r_nb = np.stack([np.stack([cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy], -1),
                     np.stack([cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy], -1),
                     np.stack([-sp, sr * cp, cr * cp], -1)], -2)
    return np.einsum("nji,j->ni", r_nb, ned_mg)


def write_log(path, with_priorities=True, learnt_offset_mg=None):
    """The synthetic 4.x log; ``learnt_offset_mg`` (slot 1's) is what the firmware applied and
    logged in MAG Ofs while the parameters still say otherwise (offsets learnt in flight)."""
    w = ap4_writer()
    w.write("MSG", 1000, "ArduCopter V4.5.7 (2a3dc4b7)")
    w.write("MSG", 1001, "Frame: QUAD/X")
    params = {"COMPASS_MOTCT": 0.0, "AHRS_TRIM_X": 0.0, "AHRS_TRIM_Y": 0.0, "AHRS_TRIM_Z": 0.0}
    for slot, (dev, ext, ofs, dia, odi) in SLOTS.items():
        sfx = "" if slot == 0 else str(slot + 1)
        params[f"COMPASS_DEV_ID{sfx}"] = dev
        params["COMPASS_EXTERNAL" if slot == 0 else f"COMPASS_EXTERN{slot + 1}"] = ext
        for kind, v in (("OFS", ofs), ("DIA", dia), ("ODI", odi), ("MOT", (0.0, 0.0, 0.0))):
            params.update({f"COMPASS_{kind}{sfx}_{a}": v[i] for i, a in enumerate("XYZ")})
    if with_priorities:
        params.update({f"COMPASS_PRIO{i + 1}_ID": dev for i, dev in enumerate(PRIORITY)})
    for name, value in params.items():
        w.write("PARM", 2000, name, value, 0.0)
    order = PRIORITY if with_priorities else tuple(SLOTS[s][0] for s in SLOTS)
    slot_of = {SLOTS[s][0]: s for s in SLOTS}
    t = np.arange(0.0, SECONDS, 1.0 / RATE_HZ) + 5.0
    earth = _body_field_mg(t)
    rng = np.random.default_rng(4)
    roll, pitch, yaw = _attitude(t)
    for k, tk in enumerate(t):
        us = int(tk * 1e6)
        w.write("ATT", us - 300, 0, np.degrees(roll[k]), 0, np.degrees(pitch[k]), 0, np.degrees(yaw[k]), 0, 0, 3)
        if k % 2 == 0:
            w.write("GPS", us - 200, 0, 6, GPS_MS + int(tk * 1000), GPS_WEEK, 14, 0.7, LAT, LON, ALT_M, 0, 0, 0, 0, 1)
            w.write("BAT", us - 100, 0, 15.8, 15.9, 12.0, 100.0, 5.0, 25.0, 0.01, 80, 1, 100)
        for inst, dev in enumerate(order):
            slot = slot_of[dev]
            _, _, ofs, dia, odi = SLOTS[slot]
            applied = learnt_offset_mg if (slot == 0 and learnt_offset_mg is not None) else ofs
            raw = earth[k] + np.asarray(TRUE_OFFSET_UT[slot]) * 10.0 + rng.normal(0, 1.5, 3)
            logged = ap_correct(raw, applied, dia, odi)
            sample_us = us - 15_000 - 1000 * inst  # the compass's own sample, before the log write
            w.write("MAG", us + 50 * inst, inst, *logged, *np.trunc(applied), 0, 0, 0, 1, sample_us % (1 << 32))
    w.save(path)
    return t


@pytest.fixture(scope="module")
def ap4(tmp_path_factory):
    _need()
    path = tmp_path_factory.mktemp("ap4") / "ap4.bin"
    write_log(path)
    return str(path)


def test_each_mag_instance_is_matched_to_its_slot_by_device_id(ap4):
    from magcal.recordings.logs import read_log

    log = read_log(ap4)
    assert [m.device_id for m in log.mags] == list(PRIORITY)
    assert [m.slot for m in log.mags] == [1, 0, 2]
    assert [m.external for m in log.mags] == [True, False, False]
    assert "COMPASS_PRIO1_ID" in log.mags[0].slot_how and "COMPASS_DEV_ID2" in log.mags[0].slot_how


def test_the_slot_s_parameters_are_undone_and_reapplied_give_the_logged_field(ap4):
    from magcal.recordings.logs import read_log, select

    log = read_log(ap4)
    for inst in range(3):
        lm = select(log, inst)
        slot = lm.info.slot
        _, _, ofs, dia, odi = SLOTS[slot]
        again = ap_correct(lm.series.field_ut * 10.0, ofs, dia, odi)
        np.testing.assert_allclose(again, log.mag_fields[inst].values, atol=1e-6)
        assert lm.slot == slot and f"slot {slot + 1}" in lm.undone


def test_samples_are_placed_at_the_compass_s_own_time(ap4):
    from magcal.recordings.logs import read_log

    log = read_log(ap4)
    t = log.mag_fields[0].t_s
    assert np.allclose(np.diff(t), 1.0 / RATE_HZ, atol=1e-6)
    assert abs(t[0] - (5.0 - 0.015)) < 1e-6  # the S field, not the time of writing


@pytest.mark.slow
def test_fit_recovers_the_offset_and_export_writes_the_device_s_slot(ap4, tmp_path):
    r = subprocess.run([sys.executable, "-m", "magcal", "fit", ap4, "--mag", "0", "--json"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    fit = json.loads(r.stdout)["fits"][0]
    assert fit["mode"] == "vector"
    np.testing.assert_allclose(fit["calibration"]["offset_ut"], TRUE_OFFSET_UT[1], atol=0.3)
    res = tmp_path / "fit.json"
    res.write_text(r.stdout)
    e = subprocess.run([sys.executable, "-m", "magcal", "export", str(res), "--ardupilot", "--json"],
                       capture_output=True, text=True)
    assert e.returncode == 0, e.stderr
    params = json.loads(e.stdout)["parameters"]
    assert json.loads(e.stdout)["slot"] == 2 and "COMPASS_OFS2_X" in params
    np.testing.assert_allclose([params[f"COMPASS_OFS2_{a}"] for a in "XYZ"],
                               -np.asarray(TRUE_OFFSET_UT[1]) * 10.0, atol=3.0)


def test_without_priorities_the_instance_is_the_slot(tmp_path):
    _need()
    from magcal.recordings.logs import read_log, select

    path = tmp_path / "old.bin"
    write_log(path, with_priorities=False)
    log = read_log(str(path))
    assert [m.slot for m in log.mags] == [0, 1, 2]
    assert [m.device_id for m in log.mags] == [SLOTS[s][0] for s in SLOTS]
    lm = select(log, 1)
    np.testing.assert_allclose(ap_correct(lm.series.field_ut * 10.0, *SLOTS[1][2:]), log.mag_fields[1].values, atol=1e-6)


def test_offsets_learnt_in_flight_are_taken_from_the_log_and_said(tmp_path):
    _need()
    from magcal.recordings.logs import read_log, select

    path = tmp_path / "learnt.bin"
    learnt = (-100.0, 70.0, 260.0)
    write_log(path, learnt_offset_mg=learnt)
    lm = select(read_log(str(path)), 1)  # MAG[1] is slot 1, whose offsets were learnt
    assert "MAG Ofs" in lm.undone
    _, _, _, dia, odi = SLOTS[0]
    again = ap_correct(lm.series.field_ut * 10.0, learnt, dia, odi)
    np.testing.assert_allclose(again, lm.log.mag_fields[1].values, atol=1e-6)


def test_newer_numbered_parameter_names_are_read_and_written(tmp_path):
    """Newer firmware names the per-compass parameters COMPASS2_OFS_X (AP_Compass_Params)."""
    _need()
    from magcal.recordings.logs import conventions as cv

    old = {"COMPASS_OFS2_X": 5.0, "COMPASS_DEV_ID2": 97539, "COMPASS_EXTERN2": 1}
    new = {"COMPASS1_OFS_X": 1.0, "COMPASS2_OFS_X": 5.0, "COMPASS2_DEV_ID": 97539, "COMPASS2_EXTERN": 1}
    for params in (old, new):
        assert cv.ap_compass(params, 1).ofs_mg[0] == 5.0
        assert params[cv.ap_slot_param("DEV_ID", 1, params)] == 97539
        assert params[cv.ap_slot_param("EXTERNAL", 1, params)] == 1
    from magcal.core.calibration import Calibration

    cal = Calibration(offset_ut=[1.0, 2.0, 3.0], field_ut=50.0, soft_iron=np.eye(3))
    assert "COMPASS2_OFS_X" in cv.to_ardupilot(cal, 1, None, numbered=True)
    assert "COMPASS_OFS2_X" in cv.to_ardupilot(cal, 1, None)
