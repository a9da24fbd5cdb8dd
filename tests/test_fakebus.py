"""The fake I2C bus, behaviour by behaviour, each driven through the real i2c backend.

The fake is the C register model (firmware/emulator/mpu9150_model.c) fed by the physics
simulator; these tests pin the chip behaviours the backend relies on or must survive.
"""

from __future__ import annotations

import errno

import numpy as np
import pytest
from i2c_support import BurstHookBus, opened, samples

from magcal.core.errors import PortUnavailable
from magcal.core.events import Event
from magcal.core.sample import UT_PER_COUNT, asa_gain
from magcal.devices.fakebus import FakeBus, FakeClock
from magcal.devices.i2c import AK_ADDR, MODE_SINGLE, REG_ASAX, REG_CNTL, REG_HXL, REG_ST1
from magcal.sim.physics import Motion, Physics, Scenario, demo_scenario


def test_each_address_has_its_own_registers_and_ad0_selects_the_mpu():
    bus = FakeBus(demo_scenario(2), address=0x69)
    dev = opened(bus, "i2c:1?addr=0x69")
    assert dev.identity.who_am_i == 0x68  # WHO_AM_I is 0x68 whatever AD0 is
    assert dev.identity.extra["address"] == "0x69"
    # The MPU's and the AK8975's register 0x00 are different registers.
    assert bus.read_byte_data(AK_ADDR, 0x00) == 0x48
    assert bus.read_byte_data(0x69, 0x75) == 0x68
    with pytest.raises(PortUnavailable, match=r"0x68.*addr=0x69"):
        opened(FakeBus(demo_scenario(2), address=0x69), "i2c:1")


def test_ak8975_nacks_with_errno_121_until_the_backend_turns_bypass_on():
    bus = FakeBus(demo_scenario(2))
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(AK_ADDR, 0x00)
    assert exc.value.errno == errno.EREMOTEIO == 121
    dev = opened(bus)
    assert dev.identity.wia == 0x48
    assert bus.read_byte_data(AK_ADDR, 0x00) == 0x48
    # Turning the aux I2C master back on hides the AK8975 again.
    bus.write_byte_data(0x68, 0x6A, 0x20)
    with pytest.raises(OSError):
        bus.read_byte_data(AK_ADDR, 0x00)


def test_drdy_rises_only_after_the_measurement_delay_on_the_injected_clock():
    bus = FakeBus(demo_scenario(2), measure_us=7300)
    dev = opened(bus)
    dev.start(50)
    got = samples(dev.read(0.21))
    assert len(got) == 11  # 50 Hz for 0.21 s of simulated time
    # By hand on the same bus: DRDY is low until 7.3 ms after the trigger.
    clock = bus.clock
    bus.write_byte_data(AK_ADDR, REG_CNTL, MODE_SINGLE)
    t0 = clock()
    clock.sleep(0.0072 - (clock() - t0))
    assert bus.read_byte_data(AK_ADDR, REG_ST1) & 1 == 0
    clock.sleep(0.0002)
    assert bus.read_byte_data(AK_ADDR, REG_ST1) & 1 == 1


def test_a_slower_chip_still_yields_every_sample_because_the_backend_polls_drdy():
    bus = FakeBus(demo_scenario(2), measure_us=15000)
    dev = opened(bus)
    dev.start(20)
    got = samples(dev.read(1.01))
    assert len(got) == 21
    assert dev.counters["drdy_timeout"] == 0
    assert bus.measurements == 21


def test_reading_the_data_registers_clears_drdy_and_a_second_read_is_stale():
    bus = FakeBus(demo_scenario(2))
    dev = opened(bus)
    dev.start(50)
    (s,) = samples(dev.read(0.0))
    assert bus.peek(AK_ADDR, REG_ST1) & 1 == 0
    again = bus.read_i2c_block_data(AK_ADDR, REG_HXL, 6)
    raw = [int.from_bytes(bytes(again[i : i + 2]), "little", signed=True) for i in (0, 2, 4)]
    assert tuple(raw) == s.raw  # no new trigger: the same (stale) measurement


def test_asa_is_readable_only_in_fuse_rom_mode_and_the_backend_gets_it():
    sc = demo_scenario(2).with_physics(asa=(150, 100, 201))
    bus = FakeBus(sc)
    dev = opened(bus)
    assert dev.identity.asa == (150, 100, 201)
    # After bring-up the chip is powered down: the ASA registers read 0.
    assert bus.read_i2c_block_data(AK_ADDR, REG_ASAX, 3) == [0, 0, 0]
    assert bus.peek(AK_ADDR, REG_CNTL) == 0x00


def test_a_read_during_a_measurement_sets_derr_and_the_backend_rejects_it():
    # something else on the bus starts a new measurement just before our burst read
    bus = BurstHookBus(demo_scenario(2), lambda b: b.write_byte_data(AK_ADDR, REG_CNTL, MODE_SINGLE))
    dev = opened(bus)
    dev.start(50)
    items = dev.read(0.1)
    assert not samples(items)
    rejected = [i for i in items if isinstance(i, Event) and i.kind == "rejected"]
    assert rejected and all(e.detail.startswith("derr") for e in rejected)
    assert dev.counters["rejected_derr"] == len(rejected) == dev.counters["measurements"]


def test_overflow_sets_hofl_clamps_the_registers_and_is_rejected_as_an_event():
    big = Scenario(Physics(hard_iron_ut=(1600.0, -100.0, 900.0), noise_ut=0.1), Motion("still"), seed=3)
    bus = FakeBus(big)
    dev = opened(bus)
    dev.start(50)
    items = dev.read(0.1)
    assert not samples(items)
    assert [e.detail.split(":")[0] for e in items] == ["hofl"] * len(items) and items
    assert dev.counters["rejected_hofl"] == len(items)
    assert all(e.seq == k for k, e in enumerate(items))  # seq still counts measurements
    hx = bus.peek(AK_ADDR, 0x03) | bus.peek(AK_ADDR, 0x04) << 8
    assert hx == 4095  # 1600 µT / (0.3 µT·gain) is past the rail: clamped
    assert bus.peek(AK_ADDR, 0x09) & 0x08


def test_burst_reads_wrap_at_astc_and_at_asaz():
    bus = FakeBus(demo_scenario(2))
    opened(bus)
    # 0x0B (reserved), 0x0C ASTC, then wrap to 0x00 WIA, 0x01 INFO
    assert bus.read_i2c_block_data(AK_ADDR, 0x0B, 4)[2] == 0x48
    bus.write_byte_data(AK_ADDR, REG_CNTL, 0x0F)
    asa = list(demo_scenario(2).physics.asa)
    assert bus.read_i2c_block_data(AK_ADDR, 0x11, 4) == asa[1:] + asa[:2]


def test_the_field_comes_from_the_physics_simulator_at_the_trigger_times():
    sc = demo_scenario(5)
    bus = FakeBus(sc)
    dev = opened(bus)
    dev.start(100)
    got = samples(dev.read(0.495))
    assert len(got) == 50
    t = np.array([s.t_s for s in got])
    raw, st2, _ = sc.measure(t, np.arange(len(got)))
    assert np.array_equal(np.array([s.raw for s in got]), raw)
    gains = np.array([asa_gain(a) for a in sc.physics.asa])
    assert np.allclose([s.field_ut for s in got], raw * UT_PER_COUNT * gains)
    assert np.allclose([s.temp_c for s in got], sc.temp_c(t), atol=0.01)


def test_simulated_time_advances_only_by_sleeps_and_bus_transfers():
    clock = FakeClock(100.0)
    bus = FakeBus(demo_scenario(2), clock=clock)
    dev = opened(bus)
    t_open = clock()
    assert 100.1 <= t_open < 100.2  # the 100 ms reset wait plus a few transfers
    dev.start(25)
    got = samples(dev.read(1.99))
    assert len(got) == 50
    assert clock() == pytest.approx(t_open + 1.99, abs=1e-6)
    assert np.allclose(np.diff([s.t_s for s in got]), 0.04, atol=1e-6)


def test_combined_i2c_rdwr_messages_work_like_the_linux_driver():
    import smbus2  # a test dependency (pyproject [test])
    bus = FakeBus(demo_scenario(2))
    opened(bus)
    w = smbus2.i2c_msg.write(AK_ADDR, [0x00])
    r = smbus2.i2c_msg.read(AK_ADDR, 3)
    bus.i2c_rdwr(w, r)
    assert list(r)[0] == 0x48
    with pytest.raises(OSError):
        bus.i2c_rdwr(smbus2.i2c_msg.write(0x33, [0]))


def test_a_closed_bus_fails_like_a_closed_file():
    bus = FakeBus(demo_scenario(2))
    bus.close()
    with pytest.raises(OSError):
        bus.read_byte_data(0x68, 0x75)


def test_the_model_library_builds_with_a_plain_compiler_when_make_is_absent(tmp_path, monkeypatch):
    import ctypes
    import shutil

    from magcal.devices import fakebus

    real_which = shutil.which
    monkeypatch.setattr(fakebus.shutil, "which", lambda name: None if name == "make" else real_which(name))
    monkeypatch.delenv("CC", raising=False)
    lib = tmp_path / "libmodel.so"
    fakebus._build(lib)
    assert ctypes.CDLL(str(lib)).mpu_model_size() > 0


def test_no_c_compiler_is_a_clear_error(tmp_path, monkeypatch):
    from magcal.core.errors import DeviceError
    from magcal.devices import fakebus

    monkeypatch.setattr(fakebus.shutil, "which", lambda name: None)
    monkeypatch.delenv("CC", raising=False)
    with pytest.raises(DeviceError, match="no C compiler"):
        fakebus._build(tmp_path / "libmodel.so")
