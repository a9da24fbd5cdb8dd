"""The commands that hand out what the package carries: ``config``, ``service install`` and
``firmware flash``'s choice of tool (the wheel test, tests/test_wheel_install.py, runs them from
an installed package)."""

from __future__ import annotations

import pytest

from magcal.cli import main
from magcal.core.errors import DeviceError, PortError
from magcal.devices import firmware
from magcal.recordings.shared import shared_path


def test_config_prints_the_template_that_lists_every_setting(capsys):
    assert main(["config"]) == 0
    out = capsys.readouterr().out
    assert out == shared_path("config", "magcal.yaml").read_text() and "gates:" in out


def test_service_install_writes_the_unit_and_keeps_an_edited_config(tmp_path, capsys):
    edited = tmp_path / "etc/magcal/magcal.yaml"
    edited.parent.mkdir(parents=True)
    edited.write_text("daemon:\n  recalibrate: true\n")
    assert main(["service", "install", "--root", str(tmp_path)]) == 0
    unit = (tmp_path / "etc/systemd/system/magcal@.service").read_text()
    assert "ExecStart=" in unit and " run --port /dev/%i " in unit and "WantedBy=dev-%i.device" in unit
    assert edited.read_text() == "daemon:\n  recalibrate: true\n"
    assert "kept" in capsys.readouterr().out


def test_service_install_into_a_missing_root_says_so(tmp_path, capsys):
    assert main(["service", "install", "--root", str(tmp_path / "nowhere")]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_flashing_uses_avrdude_else_arduino_cli_else_says_what_to_install(monkeypatch, tmp_path):
    hexfile = tmp_path / "fw.hex"
    have = {"avrdude", "arduino-cli"}
    monkeypatch.setattr(firmware.shutil, "which", lambda tool: f"/usr/bin/{tool}" if tool in have else None)
    assert firmware.flash_command("/dev/ttyACM0", hexfile)[:1] == ["avrdude"]
    have.discard("avrdude")
    cmd = firmware.flash_command("/dev/ttyACM0", hexfile)
    assert cmd[:2] == ["arduino-cli", "upload"] and str(hexfile) in cmd
    have.clear()
    with pytest.raises(DeviceError, match="avrdude"):
        firmware.flash_command("/dev/ttyACM0", hexfile)
    with pytest.raises(PortError, match="--port"):
        firmware.flash_command("", hexfile)
