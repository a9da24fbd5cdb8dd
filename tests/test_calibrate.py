"""``magcal calibrate`` end to end on the simulated board, as a user runs it."""

import json

import numpy as np
import pytest

from magcal.app import config
from magcal.app.procedure import calibrate
from magcal.cli import main
from magcal.devices import open_device
from magcal.sim.physics import demo_scenario


def run_cli(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("seed", [1, 7])
def test_recovers_the_known_offset_within_three_sigma(capsys, tmp_path, seed):
    code, out, err = run_cli(capsys, "calibrate", "--port", f"sim://?pace=0&seed={seed}&eeprom={tmp_path}/e.bin", "--json")
    assert code == 0, err
    r = json.loads(out)
    assert r["written"] is True and r["verified"] is True
    truth = demo_scenario(seed).physics
    offset = np.array(r["calibration"]["offset_ut"])
    sigma = np.array(r["uncertainty"]["offset_ut"])
    err_ut = offset - np.array(truth.hard_iron_ut)
    assert np.all(np.abs(err_ut) <= 3 * sigma), f"error {err_ut} µT vs 1σ {sigma}"
    assert abs(r["calibration"]["field_ut"] - truth.field_ut) < 0.5
    assert set(r) >= {"schema", "calibration", "rms_ut", "n_samples", "n_kept", "n_used", "coverage", "gates",
                      "written", "verified", "device"}
    assert r["schema"] == "magcal.calibrate/1"
    assert r["device"]["wia"] == "0x48"
    assert all(g["passed"] for g in r["gates"])


def test_the_written_calibration_is_on_the_board(capsys, tmp_path):
    eeprom = tmp_path / "e.bin"
    code, out, _ = run_cli(capsys, "calibrate", "--port", f"sim://?pace=0&eeprom={eeprom}", "--json")
    assert code == 0
    sent = json.loads(out)["calibration"]
    with open_device(f"sim://?pace=0&eeprom={eeprom}") as dev:
        dev.open()
        stored = dev.read_calibration()
    assert np.allclose(stored.offset_ut, sent["offset_ut"], atol=1e-3)
    assert np.allclose(stored.soft_iron, sent["soft_iron"], atol=1e-6)


def test_text_output_says_verified(capsys):
    code, out, _ = run_cli(capsys, "calibrate", "--port", "sim://?pace=0&seed=2")
    assert code == 0
    assert "VERIFIED" in out and "offset" in out


def test_no_write_reports_but_leaves_the_board_alone(capsys, tmp_path):
    eeprom = tmp_path / "e.bin"
    code, out, _ = run_cli(capsys, "calibrate", "--port", f"sim://?pace=0&eeprom={eeprom}", "--json", "--no-write")
    r = json.loads(out)
    assert code == 0 and r["written"] is False and r["calibration"]
    assert not eeprom.exists()


@pytest.mark.slow
def test_timeout_names_the_gate_that_failed(capsys):
    # flat turns only: the direction coverage can never pass
    code, out, _ = run_cli(
        capsys, "calibrate", "--port", "sim://?motion=yaw&pace=20", "--timeout", "2", "--json"
    )
    r = json.loads(out)
    assert code == 3
    assert r["failure"] == "timeout" and "min_coverage" in r["message"]
    assert r["written"] is False and r["calibration"] is None


@pytest.mark.parametrize("fault", ["no_write_ack", "corrupt_write"])
def test_a_write_that_is_not_acknowledged_or_echoed_wrong_is_never_reported_written(tmp_path, fault):
    settings = config.load(environ={})
    dev = open_device(f"sim://?pace=0&seed=3&eeprom={tmp_path}/e.bin")
    dev.reply_timeout_s = 0.5
    dev.open()
    old = dev.prepare(demo_scenario(9).physics.truth())
    dev.write_calibration(old)  # what was there before
    dev.board.faults[fault] = True
    outcome = calibrate(dev, settings)
    r = outcome.to_dict()
    assert r["written"] is False and r["verified"] is False
    assert r["status"] == "failed"
    if fault == "corrupt_write":
        assert r["restored_previous"] is True
    dev.board.faults.clear()
    stored = dev.read_calibration()
    # nothing bad is left behind: the previous calibration is still (or again) on the board
    assert dev.matches(old, stored)
    dev.close()


def test_a_device_that_never_answers_gives_a_clear_error_and_the_device_exit_status(capsys, monkeypatch):
    import magcal.devices.protocol_client as protocol_client

    monkeypatch.setattr(protocol_client.ProtocolDevice, "__init__", _quick_init(protocol_client.ProtocolDevice.__init__))
    code, out, err = run_cli(capsys, "calibrate", "--port", "sim://?pace=0&fault=mute", "--json")
    assert code == 5
    assert "did not identify" in err and "Traceback" not in err


def _quick_init(orig):
    def init(self, url, connect, **kw):
        kw["boot_timeout_s"] = 0.5
        orig(self, url, connect, **kw)

    return init


def test_bad_port_option_is_a_clear_error(capsys):
    code, _, err = run_cli(capsys, "calibrate", "--port", "sim://?pace=0&sed=1")
    assert code == 2 and "sed" in err  # a port string no backend takes: usage


def test_bad_config_key_is_named(capsys, tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("gates:\n  min_coverag: 0.5\n")
    code, _, err = run_cli(capsys, "calibrate", "--config", str(cfg))
    assert code == 2 and "gates.min_coverag" in err


def test_replaying_the_capture_of_a_calibration_gives_the_same_bits(capsys, tmp_path):
    cap = tmp_path / "live.cap"
    code, out, _ = run_cli(capsys, "calibrate", "--port", "sim://?pace=0&seed=6", "--record", str(cap), "--json")
    assert code == 0
    live = json.loads(out)
    code, out, _ = run_cli(capsys, "calibrate", "--port", f"replay://{cap}", "--json")
    replayed = json.loads(out)
    assert code == 4 and replayed["written"] is False  # a replay cannot store: not the verified write 0 means
    assert replayed["calibration"] == live["calibration"]
    assert replayed["uncertainty"] == live["uncertainty"]
    assert replayed["n_kept"] == live["n_kept"]
    code, out, _ = run_cli(capsys, "calibrate", "--port", f"replay://{cap}", "--json", "--no-write")
    assert code == 0 and json.loads(out)["calibration"] == live["calibration"]
