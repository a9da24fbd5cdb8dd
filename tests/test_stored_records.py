"""A stored calibration record that checks out (its CRC holds) but is no calibration — a matrix
that is not positive definite, a field radius of 0 — is named as such by show, calibrate and
run, never applied and never shown as the calibration, and a new calibration replaces it. A write
that does not verify leaves the earlier calibration, or nothing, never the record that failed.
On the simulated board and on the real firmware under the AVR emulator."""

import json
import struct

import numpy as np
import pytest
from firmware_support import require_firmware

from magcal.app import config
from magcal.app.daemon import Daemon, Decision
from magcal.cli import main
from magcal.core.calibration import RecordState
from magcal.devices import open_device
from magcal.wire.protocol import RECORD_FIELDS, record_crc

IDENTITY_W = (1_000_000, 1_000_000, 1_000_000, 0, 0, 0)
BAD = {
    "not_positive_definite": (1, 1000, 2000, 3000, 48_000, 1_000_000, -1_000_000, 1_000_000, 0, 0, 0, 0, 0, 0, 2500,
                              0, 0, 0),
    "zero_field": (1, 1000, 2000, 3000, 0, *IDENTITY_W, 0, 0, 0, 2500, 0, 0, 0),
}
WORDS = {"not_positive_definite": "positive definite", "zero_field": "field radius must be positive"}


def eeprom_with(path, values, version_byte=0x4D):
    """A 1 KiB EEPROM image holding ``values`` behind a valid CRC (the layout of docs/protocol.md)."""
    assert len(values) == RECORD_FIELDS
    blob = bytes([version_byte]) + struct.pack("<18i", *values) + struct.pack("<H", record_crc(values))
    path.write_bytes(blob + b"\xff" * (1024 - len(blob)))
    return path


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("bad", sorted(BAD))
def test_show_names_an_invalid_record_and_write_replaces_it(tmp_path, capsys, bad):
    ee = eeprom_with(tmp_path / "e.bin", BAD[bad])
    port = f"sim://?pace=0&eeprom={ee}"
    code, out, err = run_cli(capsys, "show", "--port", port)
    assert code == 1 and "INVALID" in out and WORDS[bad] in out and "Traceback" not in err
    code, out, _ = run_cli(capsys, "show", "--port", port, "--json")
    d = json.loads(out)
    assert d["calibration"] is None and d["record"]["state"] == "invalid" and WORDS[bad] in d["record"]["problem"]
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "evidence": {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}}))
    code, out, _ = run_cli(capsys, "write", str(good), "--port", port, "--json")
    w = json.loads(out)
    assert code == 0 and w["verified"] and w["previous_record"]["state"] == "invalid"
    code, out, _ = run_cli(capsys, "show", "--port", port, "--json")
    assert code == 0 and json.loads(out)["calibration"]["offset_ut"] == [1.0, 2.0, 3.0]


def test_calibrate_repairs_an_invalid_record(tmp_path, capsys):
    ee = eeprom_with(tmp_path / "e.bin", BAD["not_positive_definite"])
    port = f"sim://?pace=0&seed=4&eeprom={ee}"
    code, out, err = run_cli(capsys, "calibrate", "--port", port, "--json", "-q")
    d = json.loads(out)
    assert code == 0 and d["verified"], err
    assert run_cli(capsys, "show", "--port", port)[0] == 0


@pytest.mark.slow
def test_the_daemon_names_an_invalid_record_and_a_recalibration_replaces_it(tmp_path):
    ee = eeprom_with(tmp_path / "e.bin", BAD["not_positive_definite"])
    port = f"sim://?pace=0&seed=4&eeprom={ee}"
    settings = config.load(overrides={"port": port, "daemon": {"recalibrate": True}}, environ={})
    d = Daemon(settings, state_dir=tmp_path / "state", max_samples=6000)
    d.run()
    assert Decision.STORED_UNUSABLE in d.journal.decisions() and d.faults["stored_record_invalid"] == 1
    (found,) = d.journal.find(Decision.STORED_UNUSABLE)
    assert found["state"] == "invalid" and "positive definite" in found["problem"]
    assert Decision.WRITTEN in d.journal.decisions()
    with open_device(port) as dev:
        dev.open()
        assert dev.read_stored().state is RecordState.OK


def test_a_write_that_fails_on_a_blank_board_leaves_it_blank(tmp_path, capsys):
    """``corrupt_write`` on a blank board: the write failed (exit 4) and the wrong record stayed,
    shown by ``show`` as the stored calibration."""
    ee = tmp_path / "e.bin"
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"offset_ut": [10, 20, 30], "field_ut": 50.0, "evidence": {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}}))
    code, out, _ = run_cli(capsys, "write", str(good), "--port", f"sim://?pace=0&eeprom={ee}&fault=corrupt_write",
                           "--json")
    w = json.loads(out)
    assert code == 4 and not w["verified"] and w["discarded_unverified"] and w["restored_previous"] is True
    code, out, _ = run_cli(capsys, "show", "--port", f"sim://?pace=0&eeprom={ee}", "--json")
    d = json.loads(out)
    assert code == 1 and d["calibration"] is None and d["record"]["state"] == "none"


def test_a_write_that_fails_over_an_invalid_record_leaves_no_calibration(tmp_path, capsys):
    ee = eeprom_with(tmp_path / "e.bin", BAD["zero_field"])
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"offset_ut": [10, 20, 30], "field_ut": 50.0, "evidence": {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}}))
    code, out, _ = run_cli(capsys, "write", str(good), "--port", f"sim://?pace=0&eeprom={ee}&fault=corrupt_write",
                           "--json")
    w = json.loads(out)
    assert code == 4 and w["discarded_unverified"] and w["previous_record"]["state"] == "invalid"
    code, out, _ = run_cli(capsys, "show", "--port", f"sim://?pace=0&eeprom={ee}", "--json")
    assert code == 1 and json.loads(out)["calibration"] is None


def test_a_calibration_with_no_positive_field_is_no_calibration():
    from magcal.core.calibration import Calibration

    with pytest.raises(ValueError, match="field radius must be positive"):
        Calibration(offset_ut=[0, 0, 0], field_ut=0.0)


# -- the real firmware ------------------------------------------------------------------------------
def test_the_firmware_record_that_checks_out_but_is_no_calibration_is_named_and_replaced(tmp_path, capsys):
    require_firmware()
    ee = eeprom_with(tmp_path / "ee.bin", BAD["not_positive_definite"])
    port = f"emu://?seed=4&eeprom={ee}"
    code, out, err = run_cli(capsys, "show", "--port", port, "--json")
    d = json.loads(out)
    assert code == 1 and d["record"]["state"] == "invalid" and "Traceback" not in err
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "evidence": {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}}))
    code, out, _ = run_cli(capsys, "write", str(good), "--port", port, "--json")
    assert code == 0 and json.loads(out)["verified"]


def test_the_firmware_discards_its_record_on_request(tmp_path):
    """``D``: the EEPROM record is blank again (what the host asks after a write that did not
    verify when there is nothing to put back)."""
    require_firmware()
    from magcal.app.procedure import write_verified
    from magcal.core.calibration import Calibration
    from magcal.logic.gates import Evidence, Gates, clear_for_write

    cal = Calibration(offset_ut=np.array([1.0, 2.0, 3.0]), field_ut=48.0)
    with open_device(f"emu://?seed=4&eeprom={tmp_path / 'ee.bin'}") as dev:
        dev.open()
        assert write_verified(dev, cal, clear_for_write(Gates(), Evidence(
            tuple(cal.offset_ut), 48.0, 0.4, (0.02,) * 3, 1000, 0.8, 5.0))).verified
        assert dev.read_stored().state is RecordState.OK
        assert dev.discard_calibration().state is RecordState.NONE
        assert dev.read_stored().state is RecordState.NONE and dev.read_calibration() is None
    raw = (tmp_path / "ee.bin").read_bytes()
    assert raw[: 1 + 4 * RECORD_FIELDS + 2] == b"\xff" * (1 + 4 * RECORD_FIELDS + 2)
