"""A stored record that passes its CRC but makes no physical sense is INVALID — never applied,
and replaced by ``write`` or ``calibrate`` as a corrupt one is; a record whose reply is too long
for a protocol line is blamed on the record, not on a silent device."""

import json

import numpy as np
import pytest

from magcal.cli import main
from magcal.core.calibration import Calibration
from magcal.core.sense import record_problem
from magcal.devices.simboard import SimEeprom

EVIDENCE = {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}
TINY = [1, 0, 0, 0, 50000, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]  # soft iron 1e-6·I: every reading 0 µT
EXTREMES = [1] + [2**31 - 1] * 3 + [-(2**31)] * 14


@pytest.mark.parametrize("values, why", [(TINY, "soft iron"), (EXTREMES, "longer than a protocol line")])
def test_a_nonsense_record_is_invalid_and_a_write_replaces_it(tmp_path, capsys, values, why):
    ee = tmp_path / "ee.bin"
    SimEeprom(str(ee)).save_record(values)
    port = f"sim://?pace=0&eeprom={ee}"
    assert main(["show", "--port", port]) == 1
    out = capsys.readouterr().out
    assert "INVALID" in out and why in out
    src = tmp_path / "cal.json"
    src.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "evidence": EVIDENCE}))
    assert main(["write", str(src), "--port", port]) == 0
    capsys.readouterr()
    assert main(["show", "--port", port, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["calibration"]["offset_ut"] == [1.0, 2.0, 3.0]


@pytest.mark.parametrize("cal, word", [
    (Calibration([0, 0, 0], 50.0, np.eye(3) * 1e-6), "soft iron"),
    (Calibration([0, 0, 0], 50.0, np.diag([2.5, 0.2, 1.0])), "soft iron"),
    (Calibration([2e6, 0, 0], 50.0), "range"),
    (Calibration([0, 0, 0], 9e4), "range"),
    (Calibration([0, 0, 0], 50.0, coef_ut_per_unit={"temp_c": [5e4, 0, 0]}, reference={"temp_c": 25.0}), "coefficient"),
])
def test_what_no_calibration_can_be_is_named(cal, word):
    assert word in record_problem(cal)


def test_a_calibration_a_real_part_can_need_makes_sense():
    w = np.array([[1.08, 0.03, -0.01], [0.03, 0.93, 0.02], [-0.01, 0.02, 1.0]])
    assert record_problem(Calibration([1200.0, -300.0, 40.0], 48.0, w)) is None


def test_a_host_store_file_with_a_good_checksum_and_nonsense_inside_is_invalid(tmp_path):
    """The AK8975 on I2C keeps its calibration in a host file: the same sense check applies."""
    from magcal.core.calibration import RecordState
    from magcal.core.events import Identity
    from magcal.recordings.store import CalibrationStore, encode

    store = CalibrationStore(tmp_path)
    who = Identity(transport="i2c", who_am_i=0x68, wia=0x48)
    nonsense = Calibration([0, 0, 0], 50.0, np.eye(3) * 1e-6)
    store.path_for(who).write_bytes(encode(who, nonsense, saved_at="2026-01-01T00:00:00Z"))
    held = store.stored(who)
    assert held.state is RecordState.INVALID and "soft iron" in held.problem and held.calibration is None


def test_the_real_sketch_cuts_an_extreme_record_s_reply_and_it_is_named_invalid(tmp_path, capsys):
    """The firmware cuts a reply at the line limit (the simulator sends it whole and the link
    drops it): either way the record is INVALID, not a silent device, and a write replaces it."""
    from firmware_support import require_firmware

    require_firmware()
    ee = tmp_path / "ee.bin"
    SimEeprom(str(ee)).save_record(EXTREMES)  # the sketch keeps the same record layout
    port = f"emu://?eeprom={ee}"
    assert main(["show", "--port", port]) == 1
    assert "INVALID" in capsys.readouterr().out
    src = tmp_path / "cal.json"
    src.write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48.0, "evidence": EVIDENCE}))
    assert main(["write", str(src), "--port", port]) == 0
