"""``magcal calibrate / show / stream --port i2c:1`` end to end, against the fake bus.

``smbus2.SMBus`` is replaced by a factory that returns a ``FakeBus`` (the C register model fed
by the physics), which is exactly the seam the backend opens on real hardware.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import smbus2

from magcal.cli import main
from magcal.devices.fakebus import FakeBus
from magcal.sim.physics import demo_scenario

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def rig(monkeypatch, tmp_path):
    """i2c:1 is a fake MPU-9150 waved around by the physics; the store is a temp directory."""
    scenario = demo_scenario(11)
    buses: list[FakeBus] = []

    def factory(bus):
        assert bus == 1
        b = FakeBus(scenario)
        buses.append(b)
        return b

    monkeypatch.setattr(smbus2, "SMBus", factory)
    monkeypatch.setenv("MAGCAL_STORE_DIR", str(tmp_path / "store"))
    return scenario, buses, tmp_path / "store"


def run_json(capsys, argv):
    rc = main(argv)
    out = capsys.readouterr().out
    return rc, out


@pytest.mark.slow
def test_calibrate_on_i2c_recovers_the_offset_within_its_uncertainty_and_stores_it(rig, capsys):
    scenario, buses, store = rig
    rc, out = run_json(capsys, ["calibrate", "--port", "i2c:1", "--json"])
    report = json.loads(out)
    assert rc == 0, report
    assert report["status"] == "done" and report["written"] and report["verified"]
    got = np.array(report["calibration"]["offset_ut"])
    sigma = np.array(report["uncertainty"]["offset_ut"])
    truth = scenario.physics.truth().offset_ut
    assert np.all(sigma > 0) and np.all(sigma < 1.0)
    assert np.all(np.abs(got - truth) <= 3 * sigma), (got, truth, sigma)
    assert report["device"]["transport"] == "i2c" and report["device"]["bus"] == "/dev/i2c-1"
    assert buses[0].measurements >= report["n_samples"]
    assert len(list(store.glob("*.json"))) == 1

    # show: the stored calibration, for the same chip
    rc, out = run_json(capsys, ["show", "--port", "i2c:1", "--json"])
    shown = json.loads(out)
    assert rc == 0
    assert shown["calibration"]["offset_ut"] == report["calibration"]["offset_ut"]
    assert shown["stored_in"].startswith(str(store))

    # stream --calibrated: the corrected field lies on the Earth-field sphere
    rc, out = run_json(capsys, ["stream", "--port", "i2c:1", "--calibrated", "--count", "40", "--json"])
    lines = [json.loads(line) for line in out.splitlines()]
    samples = [d for d in lines if d["type"] == "sample"]
    assert rc == 0 and len(samples) == 40 and all(d["calibrated"] for d in samples)
    norms = np.array([d["norm_ut"] for d in samples])
    assert np.all(np.abs(norms - scenario.physics.field_ut) < 2.0)
    raw_norms = np.linalg.norm([np.array(d["raw"]) for d in samples], axis=1)
    assert np.all(raw_norms > 0)


def test_stream_without_calibration_prints_raw_microtesla(rig, capsys):
    scenario, _, _ = rig
    rc, out = run_json(capsys, ["stream", "--port", "i2c:1", "--count", "30", "--json"])
    samples = [json.loads(line) for line in out.splitlines()]
    assert rc == 0 and len(samples) == 30
    m = np.array([d["field_ut"] for d in samples])
    norms = np.linalg.norm(m - scenario.physics.hard_iron_ut, axis=1)
    assert np.all(np.abs(norms - scenario.physics.field_ut) < 5.0)
    assert not any(d["calibrated"] for d in samples)


def test_stream_text_has_a_header_and_one_line_per_sample(rig, capsys):
    rc = main(["stream", "--port", "i2c:1", "--count", "5", "--rate", "10"])
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert rc == 0 and "uncalibrated" in lines[0] and len(lines) == 6
    assert [int(line.split()[0]) for line in lines[1:]] == [0, 1, 2, 3, 4]
    assert "5 samples" in captured.err


def test_stream_calibrated_with_nothing_stored_says_so(rig, capsys):
    rc = main(["stream", "--port", "i2c:1", "--calibrated", "--count", "3"])
    err = capsys.readouterr().err
    assert rc == 1 and "no calibration stored" in err


def test_show_with_nothing_stored_exits_1_and_says_so(rig, capsys):
    rc = main(["show", "--port", "i2c:1"])
    out = capsys.readouterr().out
    assert rc == 1 and "none stored" in out and "0x48" in out


@pytest.mark.slow
def test_show_refuses_an_edited_store_file(rig, capsys):
    _, _, store = rig
    assert main(["calibrate", "--port", "i2c:1", "--json"]) == 0
    capsys.readouterr()
    (path,) = store.glob("*.json")
    path.write_text(path.read_text().replace('"field_ut": 5', '"field_ut": 6', 1))
    rc = main(["show", "--port", "i2c:1"])
    out, err = capsys.readouterr()
    # named as a corrupt record, never applied or shown as the calibration
    assert rc == 1 and "CORRUPT" in out and "checksum mismatch" in out and "Traceback" not in err


def test_calibrate_without_the_bus_device_file_exits_with_the_device_status_and_a_clear_message(monkeypatch, capsys):
    def no_such_bus(bus):  # what smbus2.SMBus(1) raises when /dev/i2c-1 is absent
        raise FileNotFoundError(2, "No such file or directory", f"/dev/i2c-{bus}")

    monkeypatch.setattr(smbus2, "SMBus", no_such_bus)
    rc = main(["calibrate", "--port", "i2c:1", "--json"])
    err = capsys.readouterr().err
    assert rc == 5
    assert "/dev/i2c-1 does not exist" in err and "Enable I2C" in err
    assert "Traceback" not in err


@pytest.mark.slow
def test_the_command_line_on_a_missing_bus_prints_one_line_not_a_traceback(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO), MAGCAL_STORE_DIR=str(tmp_path))
    proc = subprocess.run(
        [sys.executable, "-m", "magcal", "calibrate", "--port", "i2c:250"],
        capture_output=True, text=True, env=env, timeout=60,
    )
    assert proc.returncode == 5
    assert "/dev/i2c-250 does not exist" in proc.stderr and "Traceback" not in proc.stderr


def test_show_self_test_prints_each_axis_against_the_window(rig, capsys):
    rc = main(["show", "--port", "i2c:1", "--self-test"])
    out = capsys.readouterr().out
    assert rc == 0  # passed (nothing stored yet, and said so)
    assert "self-test   PASS" in out and "window [-1000, -300]" in out
    rc = main(["show", "--port", "i2c:1", "--self-test", "--json"])
    d = json.loads(capsys.readouterr().out)
    assert d["self_test"]["passed"] and d["self_test"]["axes"]["x"]["window"] == [-100, 100]


def test_show_self_test_on_a_backend_without_one_is_a_clear_error(capsys, tmp_path):
    cap = tmp_path / "run.cap"
    assert main(["record", "--port", "sim://?pace=0", "-o", str(cap), "--count", "20"]) == 0
    capsys.readouterr()
    rc = main(["show", "--port", f"replay://{cap}", "--self-test"])  # a recording cannot be tested
    assert rc == 5 and "cannot run the magnetometer self-test" in capsys.readouterr().err


def test_show_self_test_on_the_simulated_board_reads_its_physics(capsys):
    from magcal.sim.physics import demo_scenario

    rc = main(["show", "--port", "sim://?pace=0", "--self-test", "--json"])
    d = json.loads(capsys.readouterr().out)
    assert rc == 0 and d["self_test"]["passed"] and d["calibration"] is None  # passed; nothing stored yet
    assert [d["self_test"]["axes"][a]["raw"] for a in "xyz"] == list(demo_scenario().physics.self_test_raw())
