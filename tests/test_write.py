"""``magcal write``: a calibration found offline (fit, diagnose) put on a device and proved there."""

import json

import numpy as np
import pytest
from test_diagnose import _sim

from magcal.cli import main
from magcal.cli.write import calibration_from_json
from magcal.core.errors import InputError
from magcal.recordings.table import save_csv
from magcal.sim.physics import Temperature


# what a fit result says of the data behind its calibration: every gate judged, every one passed
EVIDENCE = {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_a_fit_from_a_recording_is_written_and_read_back(tmp_path, capsys):
    rec = tmp_path / "rec.cap"
    assert run_cli(capsys, "record", "--port", "sim://?pace=0&seed=4", "-o", str(rec), "--count", "2500")[0] == 0
    code, out, _ = run_cli(capsys, "fit", str(rec), "--json")
    assert code == 0
    fit_json = tmp_path / "fit.json"
    fit_json.write_text(out)
    port = f"sim://?pace=0&seed=4&eeprom={tmp_path}/e.bin"
    code, out, _ = run_cli(capsys, "write", str(fit_json), "--port", port, "--json")
    r = json.loads(out)
    assert code == 0 and r["written"] and r["verified"] and r["failure"] is None
    (fitted,) = json.loads(fit_json.read_text())["fits"]
    assert r["sent"]["offset_ut"] == pytest.approx(fitted["calibration"]["offset_ut"], abs=1e-3)
    code, out, _ = run_cli(capsys, "show", "--port", port, "--json")
    assert code == 0 and json.loads(out)["calibration"] == r["stored"]


def test_a_diagnosed_temperature_term_is_written_and_a_time_drift_is_named_and_left_out(tmp_path, capsys):
    run = _sim(77, temperature=Temperature(swing_c=20.0, period_s=60.0), temp_coef_ut_per_c=(0.1, -0.05, 0.06))
    path = tmp_path / "rec.csv"
    save_csv(run.series, path)
    code, out, _ = run_cli(capsys, "diagnose", str(path), "--json")
    d = json.loads(out)
    assert "temperature_drift" in {f["effect"] for f in d["findings"]}
    d["calibration"].setdefault("coef_ut_per_unit", {})["t_s"] = [0.001, 0.0, 0.0]  # as if a drift was found too
    src = tmp_path / "diag.json"
    src.write_text(json.dumps(d))
    code, out, _ = run_cli(capsys, "write", str(src), "--port", f"sim://?pace=0&eeprom={tmp_path}/e.bin")
    assert code == 0 and "VERIFIED" in out
    assert "left out the t_s term (a drift in time belongs to the recording" in out
    code, out, _ = run_cli(capsys, "show", "--port", f"sim://?pace=0&eeprom={tmp_path}/e.bin", "--json")
    stored = json.loads(out)["calibration"]
    assert set(stored["coef_ut_per_unit"]) == {"temp_c"}
    assert stored["coef_ut_per_unit"]["temp_c"] == pytest.approx(d["calibration"]["coef_ut_per_unit"]["temp_c"], abs=1e-3)


def test_a_write_the_device_garbles_is_not_reported_and_the_old_one_is_put_back(tmp_path, capsys):
    eeprom = f"{tmp_path}/e.bin"
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "evidence": EVIDENCE}))
    assert run_cli(capsys, "write", str(good), "--port", f"sim://?pace=0&eeprom={eeprom}")[0] == 0
    new = tmp_path / "new.json"
    new.write_text(json.dumps({"offset_ut": [10, 20, 30], "field_ut": 50.0, "evidence": EVIDENCE}))
    code, out, _ = run_cli(capsys, "write", str(new), "--port", f"sim://?pace=0&eeprom={eeprom}&fault=corrupt_write", "--json")
    r = json.loads(out)
    assert code == 4 and not r["written"] and not r["verified"] and r["restored_previous"] is True
    code, out, _ = run_cli(capsys, "show", "--port", f"sim://?pace=0&eeprom={eeprom}", "--json")
    assert json.loads(out)["calibration"]["offset_ut"] == [1.0, 2.0, 3.0]


def test_a_non_symmetric_matrix_keeps_every_field_magnitude():
    rng = np.random.default_rng(1)
    a = np.array([[0.96, 0.0, 0.0], [0.055, 0.995, 0.0], [0.005, 0.037, 1.04]])  # lower triangular
    cal, notes = calibration_from_json({"offset_ut": [0, 0, 0], "field_ut": 50.0, "soft_iron": a.tolist()})
    m = rng.normal(size=(200, 3)) * 40
    assert np.allclose(np.linalg.norm(m @ cal.soft_iron.T, axis=1), np.linalg.norm(m @ a.T, axis=1))
    assert any("polar factor" in n for n in notes)


def test_a_current_term_is_referred_to_zero_amps():
    cal, notes = calibration_from_json({"calibration": {
        "offset_ut": [1.0, 2.0, 3.0], "field_ut": 50.0,
        "coef_ut_per_unit": {"current_a": [0.5, 0.0, -1.0]}, "reference": {"current_a": 2.0}}})
    # m − o − k(I − 2) = m − (o − 2k) − kI
    assert cal.offset_ut.tolist() == [0.0, 2.0, 5.0] and cal.reference == {}
    assert any("0 A" in n for n in notes)


@pytest.mark.parametrize(
    "text, message",
    [
        ("not json", "not JSON"),
        ("[1, 2, 3]", "not a calibration"),
        ('{"calibration": null, "status": "failed"}', "empty"),
        ('{"offset_ut": [1, 2, 3]}', "lacks field_ut"),
        ('{"offset_ut": [1, 2], "field_ut": 50}', "offset_ut needs 3 numbers"),
        ('{"offset_ut": [1, 2, 3], "field_ut": -5}', "positive"),
        ('{"offset_ut": [1, 2, 3], "field_ut": 50, "soft_iron": [[1,0,0],[0,-1,0],[0,0,1]]}', "positive definite"),
        ('{"offset_ut": [3e6, 0, 0], "field_ut": 50}', "cannot hold that calibration: calibration value out of range"),
    ],
)
def test_bad_input_names_the_problem_and_stores_nothing(tmp_path, capsys, text, message):
    src = tmp_path / "cal.json"
    src.write_text(text)
    eeprom = tmp_path / "e.bin"
    # --force: past the gates (tested below), to the device's own range check
    code, _, err = run_cli(capsys, "write", str(src), "--port", f"sim://?pace=0&eeprom={eeprom}", "--force")
    assert code == 6 and message in err
    if not eeprom.exists():
        return
    # refused by the device's record format before anything was sent: nothing stored
    code, out, _ = run_cli(capsys, "show", "--port", f"sim://?pace=0&eeprom={eeprom}", "--json")
    assert json.loads(out)["calibration"] is None


def test_a_recording_cannot_be_written_to(tmp_path, capsys):
    rec = tmp_path / "rec.cap"
    assert run_cli(capsys, "record", "--port", "sim://?pace=0&seed=4", "-o", str(rec), "--count", "50")[0] == 0
    src = tmp_path / "cal.json"
    src.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "evidence": EVIDENCE}))
    code, _, err = run_cli(capsys, "write", str(src), "--port", f"replay://{rec}")
    assert code == 4 and "read-only" in err


def test_the_real_firmware_stores_a_diagnosed_temperature_term(tmp_path, capsys):
    from firmware_support import require_firmware

    require_firmware()
    src = tmp_path / "cal.json"
    cal = {"offset_ut": [23.5, -41.2, 12.8], "field_ut": 48.0, "soft_iron": [[1.01, 0.002, 0], [0.002, 0.99, 0], [0, 0, 1]],
           "coef_ut_per_unit": {"temp_c": [0.1, -0.05, 0.02]}, "reference": {"temp_c": 25.0}}
    src.write_text(json.dumps({"calibration": cal, "evidence": EVIDENCE}))
    port = f"emu://?eeprom={tmp_path}/e.bin"
    code, out, _ = run_cli(capsys, "write", str(src), "--port", port, "--json")
    r = json.loads(out)
    assert code == 0 and r["verified"]
    # a new session on the same EEPROM: the sketch kept it
    code, out, _ = run_cli(capsys, "show", "--port", port, "--json")
    stored = json.loads(out)["calibration"]
    assert stored["offset_ut"] == pytest.approx(cal["offset_ut"], abs=1e-3)
    assert stored["coef_ut_per_unit"]["temp_c"] == pytest.approx([0.1, -0.05, 0.02], abs=1e-3)
    assert stored["reference"]["temp_c"] == 25.0


def _no_calibration_stored(capsys, port) -> bool:
    code, out, _ = run_cli(capsys, "show", "--port", port, "--json")
    return code == 1 and json.loads(out)["calibration"] is None  # show: 1 when nothing is stored


def test_a_calibration_failing_the_gates_is_not_written(tmp_path, capsys):
    """A 5000 µT offset with a 5 µT field is no hard iron: refused (exit 3), nothing sent."""
    src = tmp_path / "cal.json"
    src.write_text(json.dumps({"offset_ut": [5000, 0, 0], "field_ut": 5.0}))
    port = f"sim://?pace=0&eeprom={tmp_path}/e.bin"
    code, out, _ = run_cli(capsys, "write", str(src), "--port", port, "--json")
    r = json.loads(out)
    assert code == 3 and not r["written"] and set(r["gates"]["failing"]) == {"field_range", "max_offset"}
    assert "max_rms" in r["gates"]["not_judged"]  # a bare calibration says nothing of its residuals
    assert _no_calibration_stored(capsys, port)


def test_a_fit_failing_its_gates_is_not_written_and_force_is_recorded(tmp_path, capsys):
    """A fit of a 9 µT field with a 1200 µT hard iron passes no field-range or offset gate."""
    rec = tmp_path / "rec.csv"
    assert run_cli(capsys, "simulate", "-o", str(rec), "--field", "9", "--offset", "1200,0,0", "--seconds", "30")[0] == 0
    code, out, _ = run_cli(capsys, "fit", str(rec), "--json")
    assert code == 0
    fit_json = tmp_path / "fit.json"
    fit_json.write_text(out)
    port = f"sim://?pace=0&eeprom={tmp_path}/e.bin"
    code, out, _ = run_cli(capsys, "write", str(fit_json), "--port", port)
    assert code == 3 and "FAIL  field radius" in out
    assert "not written" in out and _no_calibration_stored(capsys, port)
    code, out, err = run_cli(capsys, "write", str(fit_json), "--port", port, "--force", "--json")
    r = json.loads(out)
    assert code == 0 and r["verified"] and r["gates"]["forced"] and set(r["gates"]["failing"]) >= {"field_range", "max_offset"}
    assert "--force" in err and "FORCED" in err


def test_a_gate_read_from_the_configuration_applies_to_write(tmp_path, capsys):
    src = tmp_path / "cal.json"
    src.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "rms_ut": 3.0,
                               "evidence": {k: v for k, v in EVIDENCE.items() if k != "rms_ut"}}))
    cfg = tmp_path / "c.yaml"
    cfg.write_text("gates:\n  max_rms_ut: 4.0\n")
    port = f"sim://?pace=0&eeprom={tmp_path}/e.bin"
    assert run_cli(capsys, "write", str(src), "--port", port)[0] == 3  # 3 µT > the default 2 µT
    assert run_cli(capsys, "write", str(src), "--port", port, "--config", str(cfg))[0] == 0


def test_every_path_that_writes_needs_the_gates_clearance(tmp_path):
    """write_verified refuses a calibration without a clearance that covers it."""
    from magcal.app.procedure import write_verified
    from magcal.core.calibration import Calibration
    from magcal.devices import open_device
    from magcal.logic.gates import Evidence, Gates, clear_for_write

    bad = Calibration(offset_ut=np.array([5000.0, 0, 0]), field_ut=5.0)
    good = Calibration(offset_ut=np.array([1.0, 2, 3]), field_ut=48.0)
    refused = clear_for_write(Gates(), Evidence(tuple(bad.offset_ut), bad.field_ut))
    cleared = clear_for_write(Gates(), Evidence(tuple(good.offset_ut), good.field_ut, rms_ut=0.4,
                                                offset_sigma_ut=(0.02,) * 3, n_used=1000, coverage=0.8, condition=5.0))
    with open_device(f"sim://?pace=0&eeprom={tmp_path}/e.bin") as dev:
        dev.open()
        with pytest.raises(ValueError, match="gates did not clear"):
            write_verified(dev, bad, refused)
        with pytest.raises(ValueError, match="gates did not clear"):
            write_verified(dev, bad, cleared)  # a clearance of another calibration
        assert write_verified(dev, good, cleared).verified


@pytest.mark.parametrize("text, message", [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"offset_ut": [1, 2, 3], "field_ut": 48, "rms_ut": "small"}', "'rms_ut' must be a finite number"),
    ('{"offset_ut": [1, 2, 3], "field_ut": 48, "uncertainty": {"offset_ut": [1e999, 0, 0]}}', "'offset_ut' must be 3 finite"),
])
def test_a_malformed_result_file_is_a_named_input_error(tmp_path, capsys, text, message):
    src = tmp_path / "r.json"
    src.write_text(text)
    code, _, err = run_cli(capsys, "write", str(src), "--port", f"sim://?pace=0&eeprom={tmp_path}/e.bin")
    assert code == 6 and message in err and str(src) in err and "Traceback" not in err
