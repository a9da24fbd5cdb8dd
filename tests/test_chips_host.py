"""The chips beside the MPU-9150 on the host side: the MPU-9250/9255 (AK8963, 14- and 16-bit)
and the ICM-20948 (AK09916), each found by its ids on the behavioural I2C bus, read in its own
counts, self-tested against its own datasheet window and calibrated end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
import smbus2

from magcal.cli import main
from magcal.core.chips import ICM20948, MPU9150, MPU9250_14, MPU9250_16, chip_from_ids, chip_named
from magcal.core.errors import IdentityError, PortError
from magcal.devices.fakebus import FakeBus
from magcal.devices.port import chip_of, parse_port
from magcal.sim.physics import demo_scenario
from tests.i2c_support import opened, samples

CHIP_PORTS = [(MPU9150, "i2c:1"), (MPU9250_16, "i2c:1"), (MPU9250_14, "i2c:1?bits=14"), (ICM20948, "i2c:1")]


def test_the_table_names_each_part_by_its_ids_and_refuses_an_unknown_one():
    assert chip_from_ids(0x73, 0x48) is MPU9250_16 and chip_from_ids(0x71, 0x48, 14) is MPU9250_14
    assert chip_from_ids(0xEA, 0x09) is ICM20948 and chip_named("ICM-20948") is ICM20948
    assert MPU9150.range_ut == pytest.approx(1228.5) and MPU9250_16.range_ut == pytest.approx(4914.0)
    with pytest.raises(ValueError, match="WHO_AM_I 0x70"):
        chip_from_ids(0x70, 0x48)
    with pytest.raises(PortError, match="no 14-bit output"):
        chip_of(parse_port("sim://?chip=icm20948&bits=14"))


@pytest.mark.parametrize("chip,url", CHIP_PORTS, ids=lambda v: getattr(v, "label", v))
def test_each_chip_is_found_read_in_its_own_counts_and_self_tests_inside_its_window(chip, url):
    sc = demo_scenario(5)
    dev = opened(FakeBus(sc, chip=chip), url)
    assert dev.identity.chip == chip and dev.identity.bits == chip.bits
    assert dev.identity.asa == (sc.physics.asa if chip.has_asa else (128, 128, 128))
    dev.start(50)
    got = samples(dev.read(0.5))
    assert len(got) >= 20
    raw = np.array([s.raw for s in got], dtype=np.float64)
    ut = np.array([s.field_ut for s in got])
    gains = ut / np.where(raw == 0, np.nan, raw)  # µT per count, ASA included
    assert np.nanmedian(np.abs(gains)) == pytest.approx(chip.ut_per_count, rel=0.5)
    assert 30 < np.median(np.linalg.norm(ut - sc.physics.hard_iron_ut, axis=1)) < 70
    result = dev.self_test()
    assert result.passed and result.window == chip.self_test_window
    dev.close()


def test_a_chip_other_than_the_one_asked_for_is_refused_by_name():
    with pytest.raises(IdentityError, match=r"WHO_AM_I reads 0xEA, expected 0x68 \(MPU-9150\)"):
        opened(FakeBus(demo_scenario(2), chip=ICM20948), "i2c:1?chip=mpu9150")


@pytest.mark.parametrize("chip", [MPU9250_16, MPU9250_14, ICM20948], ids=lambda c: c.label)
def test_calibrate_on_each_new_chip_over_i2c_is_written_and_verified(chip, monkeypatch, tmp_path, capsys):
    sc = demo_scenario(11)
    monkeypatch.setattr(smbus2, "SMBus", lambda bus: FakeBus(sc, chip=chip))
    monkeypatch.setenv("MAGCAL_STORE_DIR", str(tmp_path / "store"))
    url = "i2c:1?bits=14" if chip.bits == 14 else "i2c:1"
    rc = main(["calibrate", "--port", url, "--json"])
    report = json.loads(capsys.readouterr().out)
    assert rc == 0, report
    assert report["written"] and report["verified"]
    got = np.array(report["calibration"]["offset_ut"])
    assert np.all(np.abs(got - sc.physics.hard_iron_ut) < 2.0), got


@pytest.mark.parametrize("query", ["chip=icm20948", "chip=mpu9250&bits=14"])
def test_sim_board_of_a_new_chip_is_named_self_tested_and_calibrated(query, tmp_path, capsys):
    url = f"sim://?{query}&pace=0&eeprom={tmp_path / 'ee.bin'}"
    assert main(["show", "--port", url, "--self-test"]) == 0
    shown = capsys.readouterr().out
    chip = chip_named(*(("icm20948",) if "icm" in query else ("mpu9250", 14)))
    assert f"chip        {chip.label}" in shown and f"window from the {chip.magnetometer.value} datasheet" in shown
    assert "self-test   PASS" in shown
    rc = main(["calibrate", "--port", url, "--json"])
    report = json.loads(capsys.readouterr().out)
    assert rc == 0 and report["written"] and report["verified"], report
    assert report["device"]["chip"] == chip.label
    assert np.allclose(report["calibration"]["offset_ut"], demo_scenario(1).physics.hard_iron_ut, atol=1.0)


@pytest.mark.parametrize("query", ["chip=icm20948", "chip=mpu9250&bits=14"])
def test_a_capture_of_a_new_chip_is_read_back_in_its_own_counts(query, tmp_path, capsys):
    cap = tmp_path / "board.cap"
    assert main(["record", "--port", f"sim://?{query}&pace=0", "-o", str(cap), "--count", "1500", "-q"]) == 0
    capsys.readouterr()
    assert main(["fit", str(cap), "--json"]) == 0
    cal = json.loads(capsys.readouterr().out)["fits"][0]["calibration"]
    physics = demo_scenario(1).physics
    assert np.allclose(cal["offset_ut"], physics.hard_iron_ut, atol=1.0), cal
    assert abs(cal["field_ut"] - physics.field_ut) < 1.0, cal


@pytest.mark.parametrize("query", ["chip=icm20948", "chip=mpu9250&bits=14"])
def test_a_replayed_new_chip_keeps_its_counts_across_a_board_reset(query, tmp_path, capsys):
    from magcal.app.load import load_series
    from magcal.devices import open_device
    from magcal.devices.base import read_to_end

    cap = tmp_path / "board.cap"
    assert main(["record", "--port", f"sim://?{query}&pace=0", "-o", str(cap), "--count", "300", "-q"]) == 0
    dev = open_device(f"replay://{cap}?fault=reset@0.001")  # the board resets after its first lines: its hello again
    replayed = np.array([s.field_ut for s in read_to_end(dev)])
    assert dev.counters["device_resets"] == 1
    recorded = load_series(str(cap)).field_ut  # the stream as it came, read in the chip's counts
    assert replayed.shape == recorded.shape and np.allclose(replayed, recorded, equal_nan=True)


@pytest.mark.parametrize("chip,url", CHIP_PORTS, ids=lambda v: getattr(v, "label", v))
def test_show_self_test_over_i2c_passes_inside_each_chips_window_in_the_counts_it_names(chip, url, monkeypatch,
                                                                                       tmp_path, capsys):
    monkeypatch.setattr(smbus2, "SMBus", lambda bus: FakeBus(demo_scenario(5), chip=chip))
    monkeypatch.setenv("MAGCAL_STORE_DIR", str(tmp_path / "store"))
    main(["show", "--port", url, "--self-test"])
    shown = capsys.readouterr().out
    assert f"chip        {chip.label}" in shown and "self-test   PASS" in shown, shown
    assert ("ASA-adjusted counts" in shown) == chip.has_asa, shown  # the AK09916 has no sensitivity adjustment
    assert f"window from the {chip.magnetometer.value} datasheet" in shown
    for axis, (lo, hi) in zip("xyz", chip.self_test_window):
        assert f"window [{lo}, {hi}]  ok" in shown, shown
