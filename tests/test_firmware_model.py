"""The register model's chip behaviours that the firmware's bring-up and measurement loop rely
on, driven byte by byte through the fake bus (the same C file the emulated board answers with)."""

from __future__ import annotations

import errno

import pytest

from magcal.devices.fakebus import FakeBus, FakeClock
from magcal.sim.physics import demo_scenario

MPU, AK = 0x68, 0x0C
PWR_MGMT_1, USER_CTRL, INT_PIN_CFG, TEMP_OUT_H, WHO_AM_I = 0x6B, 0x6A, 0x37, 0x41, 0x75
ST1, HXL, ST2, CNTL, ASAX = 0x02, 0x03, 0x09, 0x0A, 0x10


def _nacks(bus, addr=AK) -> bool:
    try:
        bus.read_byte_data(addr, 0x00)
    except OSError as exc:
        assert exc.errno == errno.EREMOTEIO
        return True
    return False


def _bypass_on(bus):
    bus.write_byte_data(MPU, PWR_MGMT_1, 0x01)
    bus.write_byte_data(MPU, INT_PIN_CFG, 0x02)


def test_the_magnetometer_answers_only_while_the_mpu_is_awake_in_bypass_without_aux_master():
    bus = FakeBus(demo_scenario(1))
    assert bus.read_byte_data(MPU, PWR_MGMT_1) == 0x40  # powers up asleep
    bus.write_byte_data(MPU, INT_PIN_CFG, 0x02)
    assert _nacks(bus), "bypass while asleep"
    bus.write_byte_data(MPU, PWR_MGMT_1, 0x01)
    assert not _nacks(bus)
    bus.write_byte_data(MPU, USER_CTRL, 0x20)  # I2C_MST_EN takes the aux bus back
    assert _nacks(bus)
    bus.write_byte_data(MPU, USER_CTRL, 0x00)
    assert not _nacks(bus)
    bus.write_byte_data(MPU, PWR_MGMT_1, 0x80)  # device reset: registers back to defaults
    assert bus.read_byte_data(MPU, PWR_MGMT_1) == 0x40
    assert bus.read_byte_data(MPU, INT_PIN_CFG) == 0x00
    assert _nacks(bus)
    assert bus.read_byte_data(MPU, WHO_AM_I) == 0x68


def test_only_the_configured_mpu_address_answers():
    bus = FakeBus(demo_scenario(1), address=0x69)
    assert _nacks(bus, 0x68)
    assert bus.read_byte_data(0x69, WHO_AM_I) == 0x68


def test_asa_reads_zero_outside_fuse_rom_mode():
    bus = FakeBus(demo_scenario(1))
    _bypass_on(bus)
    assert bus.read_i2c_block_data(AK, ASAX, 3) == [0, 0, 0]
    bus.write_byte_data(AK, CNTL, 0x0F)
    assert bus.read_i2c_block_data(AK, ASAX, 3) == list(demo_scenario(1).physics.asa)
    bus.write_byte_data(AK, CNTL, 0x00)
    assert bus.read_i2c_block_data(AK, ASAX, 3) == [0, 0, 0]


def test_a_second_trigger_during_a_conversion_is_ignored():
    clock = FakeClock()
    bus = FakeBus(demo_scenario(1), clock=clock, measure_us=7300)
    _bypass_on(bus)
    bus.write_byte_data(AK, CNTL, 0x01)
    clock.sleep(0.005)
    bus.write_byte_data(AK, CNTL, 0x01)  # would restart the 7.3 ms if it were honoured
    clock.sleep(0.003)
    assert bus.read_byte_data(AK, ST1) & 0x01
    assert bus.measurements == 1
    assert bus.read_byte_data(AK, CNTL) == 0x00  # back to power-down by itself


def test_temperature_is_big_endian_and_follows_each_measurement():
    clock = FakeClock()
    bus = FakeBus(demo_scenario(1), clock=clock)
    _bypass_on(bus)
    bus.write_byte_data(AK, CNTL, 0x01)
    clock.sleep(0.01)
    bus.read_i2c_block_data(AK, HXL, 7)
    hi, lo = bus.read_i2c_block_data(MPU, TEMP_OUT_H, 2)
    raw = int.from_bytes(bytes([hi, lo]), "big", signed=True)
    _, _, temp = demo_scenario(1).measure([bus.measurement_times_s[0]], [0])
    assert raw == int(temp[0])


@pytest.mark.parametrize("asa", [(0, 0, 0), (255, 255, 255), (176, 178, 166)])
def test_self_test_values_sit_inside_the_datasheet_window_for_any_asa(asa):
    clock = FakeClock()
    bus = FakeBus(demo_scenario(1).with_physics(asa=asa), clock=clock)
    _bypass_on(bus)
    bus.write_byte_data(AK, CNTL, 0x08)
    clock.sleep(0.01)
    assert bus.read_byte_data(AK, ST1) & 0x01
    b = bus.read_i2c_block_data(AK, HXL, 7)
    h = [int.from_bytes(bytes(b[i:i + 2]), "little", signed=True) for i in (0, 2, 4)]
    adj = [v * (a + 128) / 256 for v, a in zip(h, asa)]
    assert -100 <= adj[0] <= 100 and -100 <= adj[1] <= 100 and -1000 <= adj[2] <= -300, adj
    assert bus.measurements == 0, "self-test does not consume a physics measurement"
