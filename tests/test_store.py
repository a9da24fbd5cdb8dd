"""The host-side calibration store and the atomic write under it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import magcal.recordings.store as store_mod
from magcal.core.calibration import Calibration
from magcal.core.errors import StateError, WriteRejected
from magcal.core.events import Identity
from magcal.recordings.atomic import write_atomic
from magcal.recordings.store import CalibrationStore, CorruptCalibrationFile, default_dir, device_key

REPO = Path(__file__).resolve().parents[1]

IDENT = Identity(
    transport="i2c", who_am_i=0x68, wia=0x48, asa=(176, 178, 166), rate_hz=50,
    extra={"bus": "/dev/i2c-1", "address": "0x68"},
)
CAL = Calibration(
    offset_ut=[23.5, -41.2, 12.8],
    field_ut=49.7,
    soft_iron=[[1.01, 0.004, -0.002], [0.004, 0.99, 0.001], [-0.002, 0.001, 1.003]],
    coef_ut_per_unit={"temp_c": [0.05, -0.02, 0.1]},
    reference={"temp_c": 27.0},
)


def test_save_then_load_returns_the_same_calibration(tmp_path):
    s = CalibrationStore(tmp_path)
    back = s.save(IDENT, CAL)
    assert back.close_to(CAL, atol_ut=0, atol_w=0)
    loaded = s.load(IDENT)
    assert loaded.close_to(CAL, atol_ut=0, atol_w=0) and loaded.reference == {"temp_c": 27.0}
    body = json.loads(s.path_for(IDENT).read_text())
    assert body["version"] == 1 and body["format"] == "magcal.calibration"
    assert len(body["sha256"]) == 64 and body["device"]["asa"] == [176, 178, 166]


def test_nothing_stored_is_none_not_an_error(tmp_path):
    assert CalibrationStore(tmp_path / "never-made").load(IDENT) is None


def test_saving_again_replaces_the_old_calibration(tmp_path):
    s = CalibrationStore(tmp_path)
    s.save(IDENT, CAL)
    newer = Calibration(offset_ut=[1, 2, 3], field_ut=50)
    s.save(IDENT, newer)
    assert s.load(IDENT).close_to(newer)
    assert [p.name for p in tmp_path.iterdir()] == [s.path_for(IDENT).name]  # no temp files left


def test_an_edited_file_is_detected_and_never_applied(tmp_path):
    s = CalibrationStore(tmp_path)
    s.save(IDENT, CAL)
    p = s.path_for(IDENT)
    p.write_text(p.read_text().replace("23.5", "25.5"))
    with pytest.raises(CorruptCalibrationFile, match="checksum mismatch") as exc:
        s.load(IDENT)
    assert str(p) in str(exc.value) and isinstance(exc.value, StateError)


def test_a_torn_file_is_detected(tmp_path):
    s = CalibrationStore(tmp_path)
    s.save(IDENT, CAL)
    p = s.path_for(IDENT)
    p.write_bytes(p.read_bytes()[:100])
    with pytest.raises(CorruptCalibrationFile, match="not valid JSON"):
        s.load(IDENT)


def test_a_newer_version_is_refused_by_number(tmp_path):
    s = CalibrationStore(tmp_path)
    s.save(IDENT, CAL)
    p = s.path_for(IDENT)
    body = json.loads(p.read_text())
    body["version"] = 2
    p.write_text(json.dumps(body))
    with pytest.raises(CorruptCalibrationFile, match="version 2; this magcal reads version 1"):
        s.load(IDENT)


def test_a_read_back_that_differs_is_a_rejected_write(tmp_path, monkeypatch):
    s = CalibrationStore(tmp_path)
    real = store_mod.write_atomic

    def lossy(path, data):  # a file system that keeps an older content
        return real(path, store_mod.encode(IDENT, Calibration(offset_ut=[0, 0, 0], field_ut=50), "x"))

    monkeypatch.setattr(store_mod, "write_atomic", lossy)
    with pytest.raises(WriteRejected, match="read back differs"):
        s.save(IDENT, CAL)


def test_a_write_interrupted_in_process_leaves_the_old_file_valid(tmp_path, monkeypatch):
    s = CalibrationStore(tmp_path)
    s.save(IDENT, CAL)

    def power_cut(fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", power_cut)
    with pytest.raises(OSError):
        s.save(IDENT, Calibration(offset_ut=[9, 9, 9], field_ut=50))
    monkeypatch.undo()
    assert s.load(IDENT).close_to(CAL)
    assert [p.name for p in tmp_path.iterdir()] == [s.path_for(IDENT).name]


_CRASH = r"""
import os, sys
import magcal.recordings.atomic as atomic
from magcal.core.calibration import Calibration
from magcal.core.events import Identity
from magcal.recordings.store import CalibrationStore

real_write = os.write
def die_at_fsync(fd):
    os._exit(9)                      # the process dies after writing, before the rename
os.fsync = die_at_fsync
ident = Identity(transport="i2c", asa=(176, 178, 166), extra={"bus": "/dev/i2c-1", "address": "0x68"})
CalibrationStore(sys.argv[1]).save(ident, Calibration(offset_ut=[9, 9, 9], field_ut=50))
"""


def test_a_process_killed_mid_write_leaves_the_old_file_valid(tmp_path):
    s = CalibrationStore(tmp_path)
    s.save(IDENT, CAL)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", _CRASH, str(tmp_path)], env=env, capture_output=True)
    assert proc.returncode == 9, proc.stderr.decode()
    leftovers = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert leftovers, "the crash should have happened after the temp file was written"
    assert s.load(IDENT).close_to(CAL)  # the old calibration, intact; the temp file is ignored


def test_write_atomic_creates_directories_and_refuses_text(tmp_path):
    p = write_atomic(tmp_path / "a" / "b" / "f.bin", b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01"
    with pytest.raises(TypeError, match="bytes"):
        write_atomic(tmp_path / "g", "text")


def test_the_key_separates_bus_address_and_chip():
    keys = {
        device_key(IDENT),
        device_key(Identity(transport="i2c", asa=IDENT.asa, extra={"bus": "/dev/i2c-0", "address": "0x68"})),
        device_key(Identity(transport="i2c", asa=IDENT.asa, extra={"bus": "/dev/i2c-1", "address": "0x69"})),
        device_key(Identity(transport="i2c", asa=(176, 178, 167), extra={"bus": "/dev/i2c-1", "address": "0x68"})),
    }
    assert len(keys) == 4
    assert device_key(IDENT) == "i2c_i2c-1_0x68_asab0b2a6"


@given(
    transport=st.text(min_size=1, max_size=20),
    bus=st.text(max_size=30),
    asa=st.tuples(*[st.integers(0, 255)] * 3),
)
def test_every_key_is_a_plain_file_name(transport, bus, asa):
    key = device_key(Identity(transport=transport, asa=asa, extra={"bus": bus}))
    assert key and "/" not in key and "\\" not in key and not key.startswith(".")
    assert key.isascii()


def test_default_directory_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("MAGCAL_STORE_DIR", str(tmp_path / "cals"))
    assert default_dir() == tmp_path / "cals"
    assert CalibrationStore().directory == tmp_path / "cals"
    monkeypatch.delenv("MAGCAL_STORE_DIR")
    assert default_dir() == Path.home() / ".local" / "share" / "magcal" / "calibrations"


finite = st.floats(-500, 500, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(offset=st.tuples(finite, finite, finite), field=st.floats(1, 200), diag=st.tuples(*[st.floats(0.5, 2)] * 3))
def test_any_calibration_round_trips_exactly(tmp_path_factory, offset, field, diag):
    s = CalibrationStore(tmp_path_factory.mktemp("s"))
    cal = Calibration(offset_ut=offset, field_ut=field, soft_iron=np.diag(diag))
    back = s.save(IDENT, cal)
    assert np.array_equal(back.offset_ut, cal.offset_ut) and back.field_ut == cal.field_ut
    assert np.array_equal(back.soft_iron, cal.soft_iron)
