"""``magcal service install`` warns when the installation it points the unit at lies where the
unit's own sandbox (ProtectHome=yes, a dynamic user) cannot reach it."""

from pathlib import Path

from magcal.cli import service


def test_an_installation_under_a_home_directory_is_named_as_hidden_from_the_service():
    assert service.hidden_installation(Path("/home/ada/.venvs/magcal")) == Path("/home")
    assert service.hidden_installation(Path("/root/venv")) == Path("/root")
    assert service.hidden_installation(Path("/run/user/1000/venv")) == Path("/run/user")
    assert service.hidden_installation(Path("/opt/magcal")) is None
    assert service.hidden_installation(Path("/usr")) is None
    assert service.hidden_installation(Path("/homestead/venv")) is None  # a prefix of the name is not inside


def test_install_from_a_home_venv_warns_on_stderr_and_still_writes_the_unit(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(service.sys, "prefix", "/home/ada/venv")
    args = type("Args", (), {"root": str(tmp_path)})()
    assert service.run(args) == 0
    out, err = capsys.readouterr()
    assert (tmp_path / "etc/systemd/system/magcal@.service").is_file()
    assert "ProtectHome=yes" in err and "/home/ada/venv" in err and "/opt/magcal" in err


def test_install_from_outside_home_directories_says_nothing_more(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(service.sys, "prefix", "/opt/magcal")
    args = type("Args", (), {"root": str(tmp_path)})()
    assert service.run(args) == 0
    assert "warning" not in capsys.readouterr().err
