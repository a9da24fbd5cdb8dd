"""The ``emu://`` backend's own logic, none of which needs the AVR toolchain."""

from __future__ import annotations

import pytest

from magcal.core.errors import DeviceError, PortError
from magcal.devices import emulator, open_device, parse_port
from magcal.devices.port import scenario_of
from magcal.sim.physics import demo_scenario


def test_a_missing_build_without_toolchain_is_a_clear_device_error(tmp_path, monkeypatch):
    monkeypatch.setattr(emulator, "ELF", tmp_path / "none.elf")
    monkeypatch.setattr(emulator, "HARNESS", tmp_path / "none-emu")
    monkeypatch.setattr(emulator, "ARDUINO_CORE", tmp_path / "no-arduino")
    with pytest.raises(DeviceError) as e:
        open_device("emu://?seed=1")
    msg = str(e.value)
    assert "no-arduino" in msg and "gcc-avr" in msg and "simavr" in msg


def test_the_url_chooses_the_physics():
    sc = scenario_of(parse_port("emu://?seed=7&offset=100,-50.5,3&noise=0.1"))
    base = demo_scenario(7)
    assert sc.seed == 7
    assert sc.physics.hard_iron_ut == (100.0, -50.5, 3.0)
    assert sc.physics.noise_ut == 0.1
    assert sc.physics.distortion == base.physics.distortion
    assert scenario_of(parse_port("emu://")) == demo_scenario(1)


@pytest.mark.parametrize("query, words", [
    ("seed=x", "seed"),
    ("offset=1,2", "offset"),
    ("noise=loud", "noise"),
    ("faults=4", "faults"),
    ("fault=unplug", "unplug"),
    ("pace=2", "pace"),
])
def test_bad_url_options_say_which(query, words):
    with pytest.raises(PortError, match=words):
        open_device(f"emu://?{query}")


def test_the_emulated_board_speaks_only_protocol_v1():
    with pytest.raises(PortError, match="motioncal"):
        open_device("emu://", dialect="motioncal")
