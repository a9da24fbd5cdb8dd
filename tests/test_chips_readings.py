"""Each chip's own reading of what is not the field: its die temperature (TEMP_OUT by that
part's formula, the same through the simulator, the emulated board, the serial client, a
capture and the I2C backend) and its rails (a count at either end of that part's range, not
the AK8975's ±4095)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.cli import main
from magcal.core.chips import CHIPS, MPU9150
from magcal.core.sample import Sample
from magcal.devices import open_device
from magcal.devices.base import read_to_end
from magcal.devices.emulator import EmulatedBoard, emu_chip
from magcal.devices.fakebus import FakeBus
from magcal.sim.physics import Temperature, demo_scenario
from tests.i2c_support import opened, samples

DIE_C = 47.5  # far from every formula's zero, so a wrong formula reads degrees off
DEMO_DIE_C = (25.5, 28.6)  # demo_scenario: 27 °C and a 1.5 °C swing


def _board_at(chip, temp_c: float = DIE_C):
    return replace(demo_scenario(3).on_chip(chip), temperature=Temperature(base_c=temp_c))


def _one_step(chip) -> float:
    return 1.0 / chip.temp_lsb_per_c


@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.label)
def test_a_known_die_temperature_round_trips_through_each_chips_registers(chip):
    for temp_c in (-20.0, 21.0, DIE_C, 80.0):
        assert chip.temp_c(chip.temp_raw(temp_c)) == pytest.approx(temp_c, abs=_one_step(chip))
    sc = _board_at(chip)
    temp_raw = int(sc.measure(np.array([0.0]), np.array([0]))[2][0])  # the simulator's TEMP_OUT
    assert temp_raw == chip.temp_raw(DIE_C)
    board = EmulatedBoard(sc, chip=emu_chip(chip.name, chip.bits))  # what the emulated board serves
    assert board.measure(0.0, 0)[2] == temp_raw
    got = samples(_i2c_read(sc, chip))
    assert got and all(s.temp_c == pytest.approx(DIE_C, abs=_one_step(chip)) for s in got)


def _i2c_read(sc, chip):
    url = "i2c:1?bits=14" if chip.bits == 14 else "i2c:1"
    dev = opened(FakeBus(sc, chip=chip), url)
    dev.start(50)
    items = dev.read(0.2)
    dev.close()
    return items


@pytest.mark.parametrize("query", ["chip=mpu9150", "chip=mpu9250&bits=14", "chip=icm20948"])
def test_a_capture_and_its_replay_read_the_boards_die_temperature(query, tmp_path, capsys):
    cap = tmp_path / "board.cap"
    assert main(["record", "--port", f"sim://?{query}&pace=0&eeprom=none", "-o", str(cap), "--count", "200",
                 "-q"]) == 0
    capsys.readouterr()
    recorded = load_series(str(cap)).channels["temp_c"]
    live = np.array([s.temp_c for s in read_to_end(open_device(f"replay://{cap}")) if isinstance(s, Sample)])
    assert len(live) == len(recorded) and np.allclose(live, recorded)
    assert DEMO_DIE_C[0] < recorded.min() and recorded.max() < DEMO_DIE_C[1], (recorded.min(), recorded.max())


@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: c.label)
def test_each_chip_rails_at_the_ends_of_its_own_range(chip):
    inside = (chip.count_max - 1, chip.count_min + 1, 5)
    assert Sample(seq=0, t_s=0.0, field_ut=(0.0, 0.0, 0.0), raw=inside, chip=chip).valid
    for rail in ((chip.count_max, 0, 1), (0, chip.count_min, 1)):
        assert not Sample(seq=0, t_s=0.0, field_ut=(0.0, 0.0, 0.0), raw=rail, chip=chip).valid
    wide = (MPU9150.count_max + 100, 0, 1)  # past the AK8975's rail, well inside a 16-bit part's
    assert Sample(seq=0, t_s=0.0, field_ut=(0.0, 0.0, 0.0), raw=wide, chip=chip).valid == (chip is not MPU9150)


def test_a_strong_field_inside_a_16_bit_range_is_kept_in_a_capture(tmp_path, capsys):
    # 800 µT of hard iron: 5300 counts on an AK09916 (range ±32752), past the AK8975's ±4095
    cap = tmp_path / "strong.cap"
    port = "sim://?chip=icm20948&pace=0&eeprom=none&offset=800,0,0"
    assert main(["record", "--port", port, "-o", str(cap), "--count", "200", "-q"]) == 0
    capsys.readouterr()
    s = load_series(str(cap))
    assert np.asarray(s.valid).all()
    assert abs(np.median(s.field_ut[:, 0]) - 800.0) < 80.0
