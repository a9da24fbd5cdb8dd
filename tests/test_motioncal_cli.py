"""``magcal calibrate --dialect motioncal`` end to end, and MotionCal logs read offline."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from adafruit_device import AdafruitBoard

from magcal.app.load import load_series
from magcal.cli import main
from magcal.fit import fit_calibration
from magcal.wire import motioncal as mc


def run_json(argv, capsys) -> tuple[int, dict]:
    rc = main(argv)
    out = capsys.readouterr().out
    return rc, json.loads(out)


def unit_map(offset, soft_iron, field):
    """The correction scaled to the unit sphere: comparable between fits whatever splits the
    overall scale between W and |B|."""
    return np.asarray(offset, float), np.asarray(soft_iron, float) / float(field)


def test_calibrate_over_motioncal_recovers_the_board_and_verifies_the_echo(capsys, tmp_path):
    cap = tmp_path / "session.cap"
    with AdafruitBoard(noise=0.02, torn=0.02, cal_period=40, lines_per_s=4000, seed=2) as board:
        rc, rep = run_json(["calibrate", "--port", board.port, "--dialect", "motioncal", "--json",
                            "--timeout", "60", "--record", str(cap)], capsys)
        stored = struct.pack("<3f", *board.mag_hardiron), board.mag_softiron, board.mag_field
        n_stored, n_bad = board.packets_stored, board.crc_failures
    assert rc == 0, rep["message"]
    assert rep["status"] == "done" and rep["written"] and rep["verified"]
    assert rep["device"]["transport"] == "motioncal"
    assert rep["link"]["echo_verified"] == 1 and rep["link"]["malformed"] > 0
    cal = rep["calibration"]
    truth = board.scenario.physics.truth()
    o, w = unit_map(cal["offset_ut"], cal["soft_iron"], cal["field_ut"])
    o_t, w_t = unit_map(truth.offset_ut, truth.soft_iron, truth.field_ut)
    assert np.abs(o - o_t).max() < 0.3  # µT, with 0.3 µT noise and a few hundred samples
    assert np.abs(w - w_t).max() * truth.field_ut < 0.01
    # what the board holds is the reported calibration (float32, its own 3×3 layout)
    # (a torn Cal line that met an ending can force a resend; every packet sent must check)
    assert n_stored == rep["link"]["packets_sent"] and n_bad == 0
    hard, soft, field = stored
    assert np.allclose(struct.unpack("<3f", hard), cal["offset_ut"], atol=1e-4)
    assert np.allclose(np.reshape(soft, (3, 3)), cal["soft_iron"], atol=1e-6)
    assert field == pytest.approx(cal["field_ut"], abs=1e-4)
    # the recorded bytes replay to the same readings offline
    replayed = load_series(cap)
    assert len(replayed) >= rep["n_samples"]


@pytest.mark.slow
def test_motioncal_report_has_the_native_shape(capsys):
    """Scripts that read the native protocol's JSON read this one unchanged."""
    rc_n, native = run_json(["calibrate", "--port", "sim://?pace=0", "--json", "--timeout", "60"], capsys)
    with AdafruitBoard(cal_period=40, lines_per_s=4000) as board:
        rc_m, mcal = run_json(["calibrate", "--port", board.port, "--dialect", "auto", "--json",
                               "--timeout", "60"], capsys)
    assert rc_n == rc_m == 0
    assert set(mcal) == set(native)
    assert set(mcal) == set(native)
    assert set(mcal["calibration"]) == set(native["calibration"])
    assert set(mcal["device"]) >= set(native["device"])


def test_wrong_echo_exits_nonzero_and_says_which_value(capsys):
    with AdafruitBoard(echo="wrong", cal_period=40, lines_per_s=4000) as board:
        rc, rep = run_json(["calibrate", "--port", board.port, "--dialect", "motioncal", "--baud", "230400",
                            "--json", "--timeout", "60"], capsys)
    assert rc == 4
    assert rep["device"]["baud"] == 230400  # not fixed at 115200
    assert not rep["verified"] and not rep["written"]
    assert rep["failure"] == "write_failed" and "hard_iron_x" in rep["message"]


# -- offline --------------------------------------------------------------------------------
SENSOR_DETAILS = [  # what Adafruit_Sensor::printSensorDetails() prints, once per sensor
    b"------------------------------------", b"Sensor:       LSM6DSOX_A", b"Type:         Acceleration (m/s2)",
    b"Driver Ver:   1", b"Unique ID:    1", b"Min Value:    -156.91", b"Max Value:    156.91",
    b"Resolution:   0.06", b"------------------------------------", b"",
]


def write_adafruit_log(path, board_seed: int = 4, n: int = 1500) -> np.ndarray:
    """A serial-monitor capture of the Adafruit sketch: banner, Raw:/Uni: pairs, Cal lines,
    a torn line now and then; returns the true readings (µT) behind it."""
    from adafruit_device import adafruit_scenario

    sc = adafruit_scenario(seed=board_seed)
    run = sc.simulate(n, rate_hz=50)
    m, _ = sc.field_ut(run.series.t_s, np.arange(n))
    out = [b"Adafruit AHRS - IMU Calibration!", b"Calibration filesys test",
           b"No calibration loaded/found... will start with defaults"] + SENSOR_DETAILS * 3
    for i, v in enumerate(m):
        c = np.round(v * 10).astype(int)
        out.append(b"Raw:0,0,8192,0,0,0,%d,%d,%d" % tuple(c))
        uni = b"Uni:0.00,0.00,9.80,0.0000,0.0000,0.0000," + ",".join(f"{x:.2f}" for x in v).encode()
        out.append(uni[: len(uni) // 2] if i % 97 == 5 else uni)
        if i % 100 == 50:
            out.append(b"Cal1:0.000,0.000,0.000,0.000,0.000,0.000,0.000,0.000,0.000,50.000")
    path.write_bytes(b"\r\n".join(out) + b"\r\n")
    return m


def test_saved_motioncal_log_reads_and_fits(tmp_path):
    p = tmp_path / "adafruit.txt"
    m = write_adafruit_log(p)
    s = load_series(p)
    assert len(s) >= len(m) - 20  # a torn Uni: line costs its reading
    assert np.abs(s.field_ut - np.round(m[: len(s)], 2)).max() > 0  # sanity: they are real data
    res = fit_calibration(s.field_ut)
    assert res, res
    truth = __import__("adafruit_device").adafruit_scenario(seed=4).physics.truth()
    cal = res.calibration
    assert np.abs(cal.offset_ut - truth.offset_ut).max() < 0.3


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_fit_and_diagnose_read_a_motioncal_log(tmp_path, capsys, command):
    p = tmp_path / "motioncal.log"
    write_adafruit_log(p)
    rc = main([command, str(p), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["schema"] == f"magcal.{command}/1"
    if command == "fit":
        (out,) = out["fits"]
    truth = __import__("adafruit_device").adafruit_scenario(seed=4).physics.truth()
    assert np.abs(np.array(out["calibration"]["offset_ut"]) - truth.offset_ut).max() < 0.3
    if command == "diagnose":
        assert out["n_samples"] == len(load_series(p))
        assert "soft_iron" in [f["effect"] for f in out["findings"]]  # the board has 6 % cross terms
    else:
        assert out["model"] == "ellipsoid"


@pytest.mark.slow
@pytest.mark.parametrize("dialect", ["motioncal", "auto"])
def test_a_recorded_motioncal_session_replays_as_it_was_live(capsys, tmp_path, dialect):
    """``record`` keeps a MotionCal sketch's bytes; ``replay://`` and ``fit FILE`` then read the
    same readings, timed by when their bytes arrived, and a replay refuses to store."""
    from magcal.core.errors import DeviceError
    from magcal.devices import open_device
    from magcal.devices.base import read_to_end

    cap = tmp_path / "mc.cap"
    with AdafruitBoard(noise=0.02, torn=0.02, lines_per_s=400, seed=5) as board:
        rc, rep = run_json(["record", "--port", board.port, "--dialect", dialect, "-o", str(cap),
                            "--count", "600", "--json"], capsys)
    assert rc == 0 and rep["n_samples"] >= 600
    replayed = read_to_end(open_device(f"replay://{cap}"))
    assert len(replayed) >= rep["n_samples"]  # (the readings the last read still held are in the file too)
    t = np.array([s.t_s for s in replayed])
    assert np.all(np.diff(t) >= 0) and 0.5 < t[-1] - t[0] < 10  # ~600 readings at ~400 lines/s, not indices
    offline = load_series(cap)
    assert np.array_equal(offline.field_ut, np.array([s.field_ut for s in replayed]))
    assert np.array_equal(offline.t_s, t)
    dev = open_device(f"replay://{cap}")
    dev.open()
    assert dev.identity.transport == "replay" and not dev.abilities.store and not dev.abilities.live
    with pytest.raises(DeviceError, match="cannot store"):
        dev.write_calibration(fit_calibration(offline.field_ut, model="sphere").calibration)
    dev.close()
