"""Flight logs: reading (ArduPilot DataFlash, PX4 ULog), undoing the log's own calibration by the
autopilot's formula, damaged files, fitting against the expected field, and the parameters out.

The autopilot formulas are written out here from their sources, independently of
magcal.recordings.logs.conventions, so the round trips test magcal against the autopilot:
ArduPilot ``AP_Compass_Backend::correct_field``: corrected = M·(s·(raw + OFS)) + MOT·x;
PX4 ``calibration::Magnetometer::Correct``: body = R·S·((raw + P·COMP) − OFF).
"""

import functools
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cli_inproc import run_magcal
from cli_once import diagnose_both_ways
from logs_extra import need

DATA = os.path.join(os.path.dirname(__file__), "data")
BIN = os.path.join(DATA, "ardupilot_log171_excerpt.bin")
ULG = os.path.join(DATA, "px4_esc_status_excerpt.ulg")


@pytest.fixture(autouse=True)
def _logs_extra():
    need("pymavlink", "pyulog", "pygeomag")


def magcal(*args):
    """``magcal ARGS`` in a new interpreter: for what must hold from one process to the next."""
    return subprocess.run([sys.executable, "-m", "magcal", *args], capture_output=True, text=True)


def one_fit(r) -> dict:
    """The single fit of ``magcal fit FILE --json`` (schema magcal.fit/1)."""
    doc = json.loads(r.stdout)
    assert doc["schema"] == "magcal.fit/1" and len(doc["fits"]) == 1
    return doc["fits"][0]


@functools.cache
def whole_samples(path) -> int:
    """The samples of magnetometer 0 in the undamaged log, as read (what ``magcal fit PATH --mag 0
    --json`` gives as ``log.magnetometer.samples``)."""
    from magcal.recordings.logs import read_log

    return read_log(path).mags[0].samples


@pytest.fixture(scope="module")
def mag1():
    """``magcal diagnose BIN --mag 1``, run once: (its JSON, its text) (cli_once)."""
    return diagnose_both_ways(BIN, "--mag", "1")


def ap_formula(raw_mg, params, suffix, x):
    """ArduPilot's correction, from its parameters by name."""
    g = lambda k, a, d: params.get(f"COMPASS_{k}{suffix}_{a}", d)  # noqa: E731
    ofs = np.array([g("OFS", a, 0.0) for a in "XYZ"])
    d, o = [g("DIA", a, 1.0) for a in "XYZ"], [g("ODI", a, 0.0) for a in "XYZ"]
    m = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    mot = np.array([g("MOT", a, 0.0) for a in "XYZ"])
    s = params.get(f"COMPASS_SCALE{suffix}", 1.0)
    return (s * (raw_mg + ofs)) @ m.T + np.outer(x, mot)


def px4_formula(raw_ga, params, n, rot, power):
    g = lambda k, a: params[f"CAL_MAG{n}_{a}{k}"]  # noqa: E731
    off = np.array([g("OFF", a) for a in "XYZ"])
    d, o = [g("SCALE", a) for a in "XYZ"], [g("ODIAG", a) for a in "XYZ"]
    s = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    comp = np.array([g("COMP", a) for a in "XYZ"])
    return ((raw_ga + np.outer(power, comp)) - off) @ s.T @ rot.T


# -- reading ----------------------------------------------------------------------------------
def test_dataflash_lists_its_compasses_and_names_channels_physically():
    from magcal.recordings.logs import read_log

    log = read_log(BIN)
    assert [m.name for m in log.mags] == ["MAG", "MAG2", "MAG3"]
    assert [m.external for m in log.mags] == [True, False, False]
    assert [m.device_id for m in log.mags] == [73225, 131874, 66826]
    assert all(9 < m.rate_hz < 11 for m in log.mags)
    ch = log.channels
    for name in ("current_a", "vbat_v", "throttle", "motor1", "motor4", "imu_temp_c", "baro_temp_c"):
        assert name in ch, name
    assert 0.3 < ch["current_a"].values.min() < 1 and 15 < ch["current_a"].values.max() < 40  # A, not cA
    assert 14 < np.median(ch["vbat_v"].values) < 17  # V, 4S
    assert 0 <= ch["throttle"].values.min() and ch["throttle"].values.max() <= 1
    assert 20 < np.median(ch["imu_temp_c"].values) < 45
    assert log.decimal_year is not None and 2015.8 < log.decimal_year < 2016.0


@pytest.mark.slow
def test_several_magnetometers_and_no_choice_lists_them():
    from magcal.cli.exits import Exit

    r = run_magcal("fit", BIN)
    assert r.returncode == Exit.USAGE and "Traceback" not in r.stderr
    for line in ("--mag 0: MAG, device id 73225", "external", "--mag 2: MAG3", "internal", "Hz"):
        assert line in r.stderr


def test_every_stream_is_on_the_magnetometer_clock_and_orientation_is_no_channel():
    from magcal.app.load import load_series

    s = load_series(BIN, mag=1)
    assert set(s.channels) >= {"current_a", "throttle", "motor1", "imu_temp_c", "baro_temp_c", "vbat_v"}
    assert not any(k.lower().startswith(("att", "roll", "pitch", "yaw", "q")) for k in s.channels)
    assert all(len(v) == len(s) for v in s.channels.values())


@pytest.mark.slow
@pytest.mark.parametrize("path, mag", [(BIN, ["--mag", "1"]), (ULG, [])], ids=["dataflash", "ulog"])
def test_a_log_read_twice_gives_identical_numbers(tmp_path, path, mag):
    runs = (magcal, run_magcal)  # a new interpreter, then this one: two processes, two hash seeds
    outs = [run("fit", path, *mag, "--json") for run in runs]
    assert outs[0].returncode == 0, outs[0].stderr
    assert one_fit(outs[0])["n_used"] > 100
    assert outs[0].stdout == outs[1].stdout
    csv = [tmp_path / f"{k}.csv" for k in range(2)]
    for run, out in zip(runs, csv):
        r = run("export", path, *mag, "-o", str(out))
        assert r.returncode == 0, r.stderr
    assert csv[0].read_bytes() == csv[1].read_bytes()


def test_ulog_reads_with_no_option_and_undoes_cal_mag():
    from magcal.recordings.logs import load_log

    lm = load_log(ULG, None)  # one magnetometer: no --mag needed
    assert lm.info.calibrated and lm.info.device_id == 396809 and lm.slot == 0
    assert "CAL_MAG0" in lm.undone
    assert {"current_a", "vbat_v", "throttle", "baro_temp_c", "esc1_current_a"} <= set(lm.series.channels)
    assert 20 < lm.series.channels["current_a"].max() < 80
    assert lm.earth_body_ut is not None


# -- the log's own calibration, undone by the autopilot's formula ---------------------------------
def test_ardupilot_undo_reapplied_by_its_formula_gives_the_logged_field():
    from magcal.recordings.logs import read_log, select

    log = read_log(BIN)
    for i, suffix in ((0, ""), (1, "2")):
        lm = select(log, i)
        raw_mg = lm.series.field_ut * 10.0
        again = ap_formula(raw_mg, log.params, suffix, np.zeros(len(raw_mg)))
        np.testing.assert_allclose(again, log.mag_fields[i].values, atol=1e-9)
        assert not np.allclose(raw_mg, log.mag_fields[i].values)  # something was undone


def test_px4_undo_reapplied_by_its_formula_gives_the_logged_field():
    from magcal.recordings.logs import conventions, read_log, select

    log = read_log(ULG)
    lm = select(log, 0)
    raw_ga = lm.series.field_ut @ lm.sensor_to_body / 100.0  # back to the sensor frame, gauss
    p = dict(log.params)
    for a in "XYZ":
        p.setdefault(f"CAL_MAG0_{a}ODIAG", 0.0)
        p.setdefault(f"CAL_MAG0_{a}COMP", 0.0)
    rot = conventions.px4_rotation(int(p["CAL_MAG0_ROT"]))
    again = px4_formula(raw_ga, p, 0, rot, np.zeros(len(raw_ga)))
    np.testing.assert_allclose(again, log.mag_fields[0].values, atol=1e-12)


# -- damaged logs -------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncate", "corrupt"])
@pytest.mark.parametrize("path", [BIN, ULG], ids=["dataflash", "ulog"])
def test_a_damaged_log_is_read_up_to_the_damage(tmp_path, path, damage):
    data = bytearray(open(path, "rb").read())
    if damage == "truncate":
        data = data[: int(len(data) * 0.6) + 7]
    else:
        rng = np.random.default_rng(1)
        mid = len(data) // 2
        data[mid: mid + 3000] = rng.integers(0, 256, 3000, dtype=np.uint8).tobytes()
    bad = tmp_path / ("bad" + os.path.splitext(path)[1])
    bad.write_bytes(bytes(data))
    from magcal.cli.exits import Exit

    r = run_magcal("fit", bad, "--mag", "0", "--json")
    assert "Traceback" not in r.stderr
    assert r.returncode in (Exit.OK, Exit.GATE), r.stderr
    d = one_fit(r)
    assert any("damaged" in w or "cut short" in w for w in d["warnings"])
    n = d["log"]["magnetometer"]["samples"]
    assert 0 < n <= whole_samples(path)
    if r.returncode == Exit.GATE:  # what survived may be too short to fit: said so, not a crash
        assert d["failure"] == "too_few_samples"
    r = run_magcal("diagnose", bad, "--mag", "0", "--json")
    assert "Traceback" not in r.stderr
    assert "damaged" in r.stderr or "cut short" in r.stderr  # the warning, whatever follows
    assert r.returncode in (Exit.OK, Exit.GATE), r.stderr  # what survived may be too short: a refusal, as fit
    if r.returncode == Exit.OK:
        assert any("damaged" in w or "cut short" in w for w in json.loads(r.stdout)["warnings"])
    else:  # too little survived to diagnose: a named reason, not a crash
        assert "magcal diagnose:" in r.stderr


@pytest.mark.slow
def test_a_file_that_only_starts_like_a_log_is_a_named_error(tmp_path):
    bad = tmp_path / "x.ulg"
    bad.write_bytes(b"ULog\x01\x12\x35" + b"\x00" * 40)
    from magcal.cli.exits import Exit

    r = run_magcal("fit", str(bad))
    assert r.returncode == Exit.INPUT and "Traceback" not in r.stderr and str(bad) in r.stderr


def test_missing_extra_is_named(monkeypatch):
    from magcal.core.errors import InputError
    from magcal.recordings.logs import read_log

    monkeypatch.setitem(sys.modules, "pyulog", None)
    with pytest.raises(InputError, match=r"magcal-mpu9150\[logs\]"):
        read_log(ULG)


# -- the fit ------------------------------------------------------------------------------------
def test_internal_compass_gets_a_current_term_the_external_none():
    from magcal.app.flightlog import fit_flight_log
    from magcal.recordings.logs import read_log, select

    log = read_log(BIN)
    results = {i: fit_flight_log(select(log, i))[0] for i in (0, 2)}
    for i, d in results.items():
        assert d["mode"] == "vector"
        cur = next(t for t in d["terms"] if t["channel"] == "current_a")
        ho = d["heldout"]
        if i == 2:  # MAG3, internal: follows the current
            assert cur["kept"] and cur["norm_ut_per_unit"] > 3 * cur["floor_ut_per_unit"]
            assert ho[cur["heldout_model"]]["rms_vector_ut"] < ho["none"]["rms_vector_ut"]
        else:  # MAG, external: no current term, or one under its floor
            assert not cur["kept"] or cur["norm_ut_per_unit"] < cur["floor_ut_per_unit"]
        assert ho[ho["chosen"]]["rms_vector_ut"] < ho["none"]["rms_vector_ut"]


@pytest.mark.slow
@pytest.mark.xdist_group("flightlogs_mag1")  # one mag1 under make test -n
def test_diagnose_tests_the_current_against_the_expected_field(mag1):
    """|m| alone cannot test a current term on a flight; diagnose on a log judges it against the
    expected field vector, and still does so where |m| alone cannot be diagnosed (level flight)."""
    found, texts = {}, {}
    for i in (0, 2):
        doc, texts[i] = diagnose_both_ways(BIN, "--mag", str(i))  # its status 0
        assert doc["schema"] == "magcal.diagnose/1" and ("findings" in doc or "magnitude_failure" in doc)
        log = doc["flight_log"]
        assert log["mode"] == "vector" and log["heldout_ut"]["chosen"] < log["heldout_ut"]["none"]
        found[i] = next(f for f in log["findings"] if f["effect"] == "current_interference")
        term = next(t for t in log["terms"] if t["channel"] == "current_a")
        assert found[i]["kept"] == term["kept"]
        if i == 0:  # external: none, or one under its floor
            assert not term["kept"] or term["norm_ut_per_unit"] < term["floor_ut_per_unit"]
        else:
            assert term["kept"] and term["norm_ut_per_unit"] > 3 * term["floor_ut_per_unit"]
    assert "finding     current_interference: current_a kept" in texts[2]
    # a |m| limit on the current (where |m| alone could not test it) points at the test below it,
    # and nothing says the current could not be tested without doing so
    text = mag1[1]
    said = [ln for ln in text.splitlines() if ln.startswith("limit       current_interference")]
    assert all("tested against the expected field below" in ln for ln in said)
    assert not [ln for ln in text.splitlines() if "following current_a could not be tested" in ln and ln not in said]
    assert "finding     current_interference: current_a kept" in text


@pytest.mark.slow
@pytest.mark.xdist_group("flightlogs_mag1")
def test_export_of_a_log_diagnosis_writes_its_vector_calibration(tmp_path, mag1):
    diag, fit = tmp_path / "diag.json", tmp_path / "fit.json"
    diag.write_text(json.dumps(mag1[0]))  # what diagnose --json printed
    fit.write_text(run_magcal("fit", BIN, "--mag", "1", "--json").stdout)
    outs = [tmp_path / "d.param", tmp_path / "f.param"]
    for src, out in zip((diag, fit), outs):
        r = run_magcal("export", str(src), "--ardupilot", "-o", str(out))
        assert r.returncode == 0, r.stderr
    values = [[ln for ln in o.read_text().splitlines() if not ln.startswith("#")] for o in outs]
    assert values[0] == values[1] and any(v.startswith("COMPASS_MOT2_X") for v in values[0])


def test_vector_fit_recovers_an_injected_calibration_from_level_flight():
    from magcal.core.calibration import Calibration
    from magcal.fit.vector import fit_vector
    from magcal.recordings.logs.conventions import euler_matrix

    rng = np.random.default_rng(7)
    n = 1500
    yaw = np.cumsum(rng.normal(0, 0.05, n))
    roll, pitch = rng.normal(0, 0.08, n), rng.normal(0, 0.08, n)  # mostly level
    ned = np.array([23.0, 5.0, -53.0])
    h = np.einsum("nji,j->ni", euler_matrix(roll, pitch, yaw), ned)
    current = 1 + 20 * (np.sin(np.arange(n) / 90.0) ** 2)
    truth = Calibration(offset_ut=[12.0, -7.0, 30.0], field_ut=np.linalg.norm(ned),
                        soft_iron=[[1.05, 0.02, -0.03], [0.02, 0.96, 0.01], [-0.03, 0.01, 1.01]],
                        coef_ut_per_unit={"current_a": [0.2, -0.4, 0.9]})
    m = truth.distort(h, {"current_a": current}) + rng.normal(0, 0.3, (n, 3))
    r = fit_vector(m, {"current_a": current}, h, np.linalg.norm(ned))
    assert r and r.mode == "vector" and r.interference_term() == "current_a"
    cal = r.calibration
    err = cal.offset_ut - truth.offset_ut
    assert np.all(np.abs(err) < 4 * r.sigma_offset_ut + 1e-3), (err, r.sigma_offset_ut)
    t = next(x for x in r.terms if x["channel"] == "current_a")
    assert np.all(np.abs(np.array(t["coef_ut_per_unit"]) - truth.coef_ut_per_unit["current_a"])
                  < 4 * np.array(t["sigma_ut_per_unit"]))
    np.testing.assert_allclose(cal.soft_iron, truth.soft_iron, atol=0.01)


def test_without_attitude_the_magnitude_is_fitted_and_says_so():
    from magcal.fit.vector import fit_vector

    rng = np.random.default_rng(3)
    u = rng.normal(size=(800, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    m = 50 * u + [5.0, -3.0, 8.0] + rng.normal(0, 0.2, (800, 3))
    r = fit_vector(m, {}, None, 50.0)
    assert r and r.mode.startswith("magnitude")
    np.testing.assert_allclose(r.calibration.offset_ut, [5.0, -3.0, 8.0], atol=0.2)


# -- parameters out: the round trip through each autopilot's formula ------------------------------
def _result_file(tmp_path, cal, autopilot, rot, slot):
    d = {"format": "magcal.fit.log/1", "model": "vector+current_a", "calibration": cal.to_dict(),
         "terms": [], "log": {"autopilot": autopilot, "sensor_to_body": np.asarray(rot).tolist(),
                              "slot": slot, "file": "flight.bin"}}
    path = tmp_path / "result.json"
    path.write_text(json.dumps(d))
    return path


def _truth():
    from magcal.core.calibration import Calibration

    return Calibration(offset_ut=[-14.0, 6.5, 41.0], field_ut=55.0,
                       soft_iron=[[0.97, 0.03, -0.02], [0.03, 1.04, 0.015], [-0.02, 0.015, 1.01]],
                       coef_ut_per_unit={"current_a": [0.31, -0.22, 0.87]}, reference={"current_a": 0.0})


def test_ardupilot_parameters_round_trip(tmp_path):
    from magcal.recordings.logs.conventions import parse_params

    cal = _truth()
    path = _result_file(tmp_path, cal, "ardupilot", np.eye(3), 1)
    r = run_magcal("export", str(path), "--ardupilot")
    assert r.returncode == 0, r.stderr
    params = parse_params((tmp_path / "result-ardupilot-2.param").read_text())
    assert params["COMPASS_MOTCT"] == 2 and "COMPASS_OFS2_X" in params
    rng = np.random.default_rng(5)
    m_ut = rng.normal(0, 40, (200, 3)) + cal.offset_ut
    current = rng.uniform(0, 30, 200)
    ours = cal.correct(m_ut, {"current_a": current})
    theirs = ap_formula(m_ut * 10.0, params, "2", current) / 10.0
    np.testing.assert_allclose(theirs, ours, atol=1e-6)


def test_px4_parameters_round_trip_through_a_rotation(tmp_path):
    from magcal.recordings.logs.conventions import parse_params, px4_rotation

    cal = _truth()
    rot = px4_rotation(2)  # yaw 90: the sensor turned in the airframe
    path = _result_file(tmp_path, cal, "px4", rot, 1)
    r = run_magcal("export", str(path), "--px4", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)["output"]
    text = open(out).read()
    assert "\t" in text  # QGroundControl's layout
    params = parse_params(text)
    assert params["CAL_MAG_COMP_TYP"] == 2
    rng = np.random.default_rng(6)
    raw_ga = rng.normal(0, 0.4, (200, 3))
    current = rng.uniform(0, 60, 200)
    ours = cal.correct(raw_ga @ rot.T * 100.0, {"current_a": current}) / 100.0  # magcal: body frame
    theirs = px4_formula(raw_ga, params, 1, rot, current / 1000.0)  # PX4: current in kA
    np.testing.assert_allclose(theirs, ours, atol=1e-7)


def test_export_of_a_log_fit_writes_the_logs_compass(tmp_path):  # make check's one run of exportparams
    r = run_magcal("fit", BIN, "--mag", "2", "--json")
    res = tmp_path / "r.json"
    res.write_text(r.stdout)
    e = run_magcal("export", str(res), "--ardupilot", "--json")
    assert e.returncode == 0, e.stderr
    d = json.loads(e.stdout)
    assert d["schema"] == "magcal.export-params/1" and d["slot"] == 3 and "COMPASS_MOT3_Z" in d["parameters"] and d["parameters"]["COMPASS_MOTCT"] == 2
    assert any("motors-running step" in n for n in d["notes"])


def test_export_refuses_what_is_not_a_fit(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text('{"hello": 1}')
    from magcal.cli.exits import Exit

    r = run_magcal("export", str(bad), "--px4", "0")
    assert r.returncode == Exit.INPUT and "not the JSON of a successful" in r.stderr and "Traceback" not in r.stderr


def test_newer_ulog_takes_the_faster_stream_and_finds_cal_mag_by_device_id():
    from magcal.recordings.logs import conventions, read_log, select

    log = read_log(os.path.join(DATA, "px4_pyulog_sample_small_mags.ulg"))
    assert [(m.device_id, m.external) for m in log.mags] == [(589858, False), (592905, True)]
    fast = log.mags[1]
    assert fast.name.startswith("vehicle_magnetometer") and fast.calibrated and fast.rate_hz > 20
    lm = select(log, 1)
    assert lm.slot == 1 and "CAL_MAG1" in lm.undone
    raw_ga = lm.series.field_ut @ lm.sensor_to_body / 100.0
    p = {**log.params, **{f"CAL_MAG1_{a}ODIAG": 0.0 for a in "XYZ"}}
    again = px4_formula(raw_ga, p, 1, conventions.px4_rotation(0), np.zeros(len(raw_ga)))
    np.testing.assert_allclose(again, log.mag_fields[1].values, atol=1e-12)
