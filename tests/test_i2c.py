"""The i2c: backend: port strings, bring-up outcomes, measuring, self-test, the store route."""

from __future__ import annotations

import re

import numpy as np
import pytest
from i2c_support import BurstHookBus, opened

from magcal.core.calibration import Calibration
from magcal.core.errors import DeviceError, IdentityError, NoReply, PortError, PortUnavailable
from magcal.core.events import Event
from magcal.core.sample import Sample
from magcal.devices import open_device, parse_port
from magcal.devices.fakebus import FakeBus
from magcal.devices.i2c import (
    AK_ADDR,
    REG_ASTC,
    REG_CNTL,
    SELF_TEST_WINDOW,
    DataNotReady,
    MagnetometerMissing,
    I2CAddress,
    SelfTestResult,
)
from magcal.sim.physics import demo_scenario


# -- port strings ------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "url, bus, path, addr",
    [
        ("i2c:1", 1, "/dev/i2c-1", 0x68),
        ("i2c:/dev/i2c-3", 3, "/dev/i2c-3", 0x68),
        ("i2c:1?addr=0x69", 1, "/dev/i2c-1", 0x69),
        ("i2c:0?addr=105", 0, "/dev/i2c-0", 0x69),
        ("i2c://22", 22, "/dev/i2c-22", 0x68),
    ],
)
def test_port_strings_name_bus_and_address(url, bus, path, addr):
    where = I2CAddress.of(parse_port(url))
    assert (where.bus, where.path, where.address) == (bus, path, addr)


@pytest.mark.parametrize(
    "url, words",
    [
        ("i2c:", "no bus"),
        ("i2c:1?addr=0x50", "0x68 (AD0 low) or 0x69"),
        ("i2c:1?addr=high", "not a number"),
        ("i2c:1?speed=3", "unknown option 'speed'"),
        ("i2c:1?rate=500", "out of range"),
    ],
)
def test_bad_port_strings_say_what_is_wrong(url, words):
    with pytest.raises(PortError, match=re.escape(words)):
        parse_port(url)


def test_the_registry_routes_i2c_urls_here():
    dev = open_device("i2c:1?addr=0x69")
    assert dev.where.address == 0x69 and dev.url == "i2c:1?addr=0x69"


# -- bring-up outcomes -------------------------------------------------------------------------
def test_bring_up_reports_the_identity_and_a_store_key():
    sc = demo_scenario(4)
    dev = opened(FakeBus(sc))
    ident = dev.identity
    assert ident.transport == "i2c"
    assert (ident.who_am_i, ident.wia, ident.asa) == (0x68, 0x48, sc.physics.asa)
    assert ident.extra == {"bus": "/dev/i2c-1", "address": "0x68"}
    assert ident.to_dict()["who_am_i"] == "0x68"


def test_a_missing_bus_device_file_is_port_unavailable_naming_the_file():
    def no_bus(n):
        raise FileNotFoundError(2, "No such file or directory", f"/dev/i2c-{n}")

    dev = open_device("i2c:7", bus_factory=no_bus)
    with pytest.raises(PortUnavailable) as exc:
        dev.open()
    msg = str(exc.value)
    assert "/dev/i2c-7 does not exist" in msg and "Enable I2C" in msg


def test_the_real_smbus2_on_a_bus_that_does_not_exist_gives_the_same_clear_error():
    dev = open_device("i2c:250")  # default factory: smbus2.SMBus(250)
    with pytest.raises(PortUnavailable, match="/dev/i2c-250 does not exist"):
        dev.open()


def test_permission_denied_says_which_group():
    def denied(n):
        raise PermissionError(13, "Permission denied")

    with pytest.raises(PortUnavailable, match="'i2c' group"):
        open_device("i2c:1", bus_factory=denied).open()


def test_wrong_who_am_i_is_an_identity_error_saying_what_was_found():
    bus = FakeBus(demo_scenario(1), faults="wrong_whoami")  # reads 0x70: an MPU-6500, no magnetometer
    with pytest.raises(IdentityError, match=r"WHO_AM_I reads 0x70, expected 0x68"):
        opened(bus, "i2c:1?chip=mpu9150")  # the user said which part to expect
    assert bus._closed  # the bus is released on failure


def test_wrong_wia_is_an_identity_error_saying_what_was_found():
    with pytest.raises(IdentityError, match=r"WIA reads 0x00, expected 0x48"):
        opened(FakeBus(demo_scenario(1), faults="wrong_wia"))


def test_a_missing_ak8975_is_named_as_such():
    with pytest.raises(MagnetometerMissing, match=r"AK8975 at 0x0C does not.*bypass"):
        opened(FakeBus(demo_scenario(1), faults=["no_ak"]))


def test_nothing_at_the_address_suggests_the_other_ad0_address():
    with pytest.raises(PortUnavailable, match=r"nothing answers at 0x69.*addr=0x68"):
        opened(FakeBus(demo_scenario(1)), "i2c:1?addr=0x69")


# -- measuring -----------------------------------------------------------------------------------
def test_a_stuck_drdy_gives_rejected_events_then_a_named_timeout():
    bus = FakeBus(demo_scenario(1))
    dev = opened(bus, drdy_timeout_s=0.03)
    dev.start(20)
    bus.set_faults("stuck_drdy")
    with pytest.raises(DataNotReady, match=r"DRDY never set within 30 ms for 3 measurements") as exc:
        dev.read(1.0)
    assert isinstance(exc.value, NoReply)
    assert dev.counters["drdy_timeout"] == 3


def test_one_missed_drdy_is_an_event_and_measuring_goes_on():
    bus = FakeBus(demo_scenario(1))
    dev = opened(bus)
    dev.start(50)
    bus.set_faults("stuck_drdy")
    first = dev.read(0.03)
    bus.set_faults(0)
    rest = dev.read(0.5)
    assert [type(i) for i in first] == [Event]
    assert first[0].kind == "rejected" and "DRDY" in first[0].detail
    assert rest and all(isinstance(i, Sample) for i in rest)
    assert rest[0].seq == first[0].seq + 1
    assert dev.counters["stale_cleared"] == 1  # the late measurement's data was read out first


def test_samples_are_asa_adjusted_counted_and_paced_by_the_rate():
    sc = demo_scenario(6)
    dev = opened(FakeBus(sc))
    dev.start(100)
    items = dev.read(0.995)
    assert len(items) == 100 and all(isinstance(s, Sample) and s.valid for s in items)
    assert [s.seq for s in items] == list(range(100))
    assert np.allclose(np.diff([s.t_s for s in items]), 0.01)
    norms = np.linalg.norm(np.array([s.field_ut for s in items]) - sc.physics.hard_iron_ut, axis=1)
    assert np.all(np.abs(norms - sc.physics.field_ut) < 5.0)  # near the sphere, not halved or doubled
    assert dev.stats()["samples"] == 100
    assert dev.identity.rate_hz == 100


def test_rate_out_of_range_is_refused():
    dev = opened(FakeBus(demo_scenario(1)))
    with pytest.raises(PortError, match="out of range"):
        dev.start(150)


def test_read_before_start_returns_nothing_and_reads_after_close_fail():
    dev = opened(FakeBus(demo_scenario(1)))
    assert dev.read(0.05) == []
    dev.close()
    with pytest.raises(DeviceError, match="closed"):
        dev.read(0.05)


def test_close_powers_the_magnetometer_down_and_releases_the_bus():
    bus = FakeBus(demo_scenario(1))
    dev = opened(bus)
    dev.start(50)
    dev.read(0.1)
    dev.close()
    assert bus.peek(AK_ADDR, REG_CNTL) == 0 and bus._closed


# -- self-test ---------------------------------------------------------------------------------------
def test_self_test_passes_on_a_healthy_chip_and_restores_astc():
    bus = FakeBus(demo_scenario(1))
    dev = opened(bus)
    result = dev.self_test()
    assert result.passed and result.axis_passed == (True, True, True)
    assert result.window == SELF_TEST_WINDOW
    assert bus.peek(AK_ADDR, REG_ASTC) == 0
    d = result.to_dict()
    assert d["passed"] and d["axes"]["z"]["window"] == [-1000, -300]


def test_self_test_judges_each_axis_against_the_window_after_asa():
    r = SelfTestResult(raw=(0, 150, -200), adjusted=(0.0, 150.0, -200.0))
    assert r.axis_passed == (True, False, False) and not r.passed
    overflow = SelfTestResult(raw=(0, 0, -500), adjusted=(0.0, 0.0, -500.0), st2=0x08)
    assert not overflow.passed


def test_self_test_on_a_stuck_chip_is_a_named_timeout():
    bus = FakeBus(demo_scenario(1))
    dev = opened(bus)
    bus.set_faults("stuck_drdy")
    with pytest.raises(DataNotReady, match="self-test"):
        dev.self_test()
    assert bus.peek(AK_ADDR, REG_ASTC) == 0


# -- calibration through the host-side store -----------------------------------------------------
def test_write_calibration_goes_to_the_store_and_reads_back(tmp_path):
    dev = opened(FakeBus(demo_scenario(1)), store_dir=tmp_path)
    assert dev.read_calibration() is None
    cal = Calibration(offset_ut=[1.5, -2.25, 3.0], field_ut=48.0, soft_iron=np.diag([1.01, 0.99, 1.0]))
    back = dev.write_calibration(cal)
    assert back.close_to(cal)
    assert dev.store_path.exists() and dev.store_path.parent == tmp_path
    again = opened(FakeBus(demo_scenario(1)), store_dir=tmp_path)
    assert again.read_calibration().close_to(cal)
    # Another chip (other ASA trim) on the same bus and address has nothing stored.
    other = opened(FakeBus(demo_scenario(1).with_physics(asa=(120, 130, 140))), store_dir=tmp_path)
    assert other.read_calibration() is None


class _DeadCoilBus(FakeBus):
    """A chip whose self-test coil produces no field: Z reads ~0 in self-test mode."""

    def read_i2c_block_data(self, addr, reg, n, force=None):
        data = super().read_i2c_block_data(addr, reg, n)
        if addr == AK_ADDR and reg == 0x03 and self.peek(AK_ADDR, REG_ASTC):
            data[4:6] = [5, 0]
        return data


def test_a_dead_self_test_coil_fails_on_the_z_axis_only():
    dev = opened(_DeadCoilBus(demo_scenario(1)))
    result = dev.self_test()
    assert result.axis_passed == (True, True, False) and not result.passed
    assert result.raw[2] == 5
    assert dev.counters["self_test_fail"] == 1


def test_a_single_bus_glitch_is_an_event_and_an_unplugged_bus_is_port_unavailable():
    bursts = iter(range(1, 1000))

    def nack_the_third(bus):  # one NACK on the third burst read (a glitch on a long cable)
        if next(bursts) == 3:
            raise OSError(121, "Remote I/O error")

    bus = BurstHookBus(demo_scenario(1), nack_the_third)
    dev = opened(bus)
    dev.start(50)
    items = dev.read(0.19)
    kinds = ["S" if isinstance(i, Sample) else i.detail.split(":")[0] for i in items]
    assert kinds == ["S", "S", "i2c error"] + ["S"] * 7
    assert dev.counters["i2c_errors"] == 1
    bus.close()  # the adapter went away
    with pytest.raises(PortUnavailable, match="stopped answering"):
        dev.read(0.1)
