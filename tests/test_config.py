import os

import pytest

from magcal.app import config
from magcal.core.errors import ConfigError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_documented_yaml_equals_the_built_in_defaults():
    assert config.to_dict(config.load(os.path.join(ROOT, "config", "magcal.yaml"), environ={})) == config.to_dict(
        config.Settings()
    )


def test_precedence_defaults_file_environment_command_line(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("port: /dev/ttyUSB0\nrate_hz: 20\ngates:\n  min_coverage: 0.7\n")
    s = config.load(str(f), environ={})
    assert (s.port, s.rate_hz, s.gates.min_coverage, s.gates.min_samples) == ("/dev/ttyUSB0", 20, 0.7, 300)
    env = {"MAGCAL_RATE_HZ": "30", "MAGCAL_GATES__MIN_COVERAGE": "0.6"}
    s = config.load(str(f), environ=env)
    assert (s.rate_hz, s.gates.min_coverage) == (30, 0.6)
    s = config.load(str(f), overrides={"rate_hz": 40, "port": None}, environ=env)
    assert (s.port, s.rate_hz) == ("/dev/ttyUSB0", 40)


def test_config_file_from_environment(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("model: sphere\n")
    assert config.load(environ={"MAGCAL_CONFIG": str(f)}).model == "sphere"


@pytest.mark.parametrize(
    "text, words",
    [
        ("colour: red\n", ["colour", "allowed"]),
        ("gates:\n  max_rms: 1\n", ["gates.max_rms"]),
        ("rate_hz: fast\n", ["rate_hz", "integer"]),
        ("rate_hz: 500\n", ["rate_hz", "[1, 100]"]),
        ("gates:\n  field_range_ut: [60, 20]\n", ["field_range_ut"]),
        ("model: cube\n", ["model", "cube"]),
        ("write: maybe\n", ["write", "true or false"]),
        ("- a\n- b\n", ["mapping"]),
        ("port: [\n", ["not valid YAML"]),
    ],
)
def test_bad_settings_are_named(tmp_path, text, words):
    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError) as exc:
        config.load(str(f), environ={})
    for w in words:
        assert w in str(exc.value)


def test_bad_environment_is_named():
    with pytest.raises(ConfigError, match="MAGCAL_.*gates.bogus"):
        config.load(environ={"MAGCAL_GATES__BOGUS": "1"})


def test_the_benchmarks_data_variables_are_not_taken_for_settings():
    """bench/README.md has the user export MAGCAL_REAL_DATA and MAGCAL_MOTIONCAL_DRIVER; a shell
    with them must still run magcal (they were refused as unknown settings), while a misspelt
    setting in the same shell is still named."""
    env = {"MAGCAL_REAL_DATA": "/data/real", "MAGCAL_MOTIONCAL_DRIVER": "/opt/mc_driver", "MAGCAL_PORT": "sim://"}
    assert config.load(environ=env).port == "sim://"
    with pytest.raises(ConfigError, match="MAGCAL_REAL_DATAS"):
        config.load(environ={"MAGCAL_REAL_DATAS": "/data/real"})


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        config.load(str(tmp_path / "nope.yaml"), environ={})


# -- every bad input a named error ---------------------------------------------------------------
def _named(exc, *words):
    text = str(exc.value)
    assert "\n" not in text and all(w in text for w in words), text


@pytest.mark.parametrize(
    "blob, words",
    [
        (bytes(range(256)) * 4, ["not UTF-8 text"]),
        (b"port: sim://\n\0\0\0", ["binary file"]),
        (b"gates: " + b"[" * 100_000 + b"]" * 100_000, ["nested too deeply"]),
        (b"1: 2\n", ["setting names are text", "1 (int)"]),
        (b"~: 2\n", ["setting names are text", "None"]),
        (b"gates: {7: 1}\n", ["setting names are text", "gates"]),
        (b"gates:\n  field_range_ut: []\n", ["gates.field_range_ut", "2 numbers"]),
        (b"gates:\n  field_range_ut: [1, 2, 3]\n", ["gates.field_range_ut", "2 numbers"]),
        (b"gates:\n  field_range_ut: [20, .nan]\n", ["gates.field_range_ut", "finite"]),
        (b"gates:\n  min_samples: 5000\n", ["gates.min_samples", "1024"]),
        (b"timeout_s: .inf\n", ["timeout_s", "finite"]),
        (b"daemon:\n  state_every_s: .nan\n", ["daemon.state_every_s", "finite"]),
        (b"daemon:\n  stall_s: -.inf\n", ["daemon.stall_s", "finite"]),
        (b"daemon:\n  capture_max_bytes: 10\n", ["daemon.capture_max_bytes", "4096"]),
        (b"baud: 1e999\n", ["baud", "integer"]),
        (b"port: \"a\\x01b\"\n", ["port", "printable"]),
        (b"x" * (2 << 20), ["larger than"]),
    ],
)
def test_a_bad_config_file_is_one_line_naming_the_file_and_the_problem(tmp_path, blob, words):
    f = tmp_path / "c.yaml"
    f.write_bytes(blob)
    with pytest.raises(ConfigError) as exc:
        config.load(str(f), environ={})
    _named(exc, str(f), *words)


def test_nesting_deeper_than_any_setting_is_refused_by_depth_before_it_is_built(tmp_path):
    """Forty levels PyYAML would build are refused for their depth, named as such (not as a
    wrong type of ``gates``); the documented depth — a list in a section — still loads."""
    f = tmp_path / "c.yaml"
    f.write_text("gates: " + "[" * 40 + "]" * 40 + "\n")
    with pytest.raises(ConfigError) as exc:
        config.load(str(f), environ={})
    _named(exc, str(f), "nested too deeply", f"{config.MAX_DEPTH} levels")
    with pytest.raises(ConfigError, match="MAGCAL_GATES__FIELD_RANGE_UT.*not a value"):
        config.load(environ={"MAGCAL_GATES__FIELD_RANGE_UT": "[" * 40 + "]" * 40})
    f.write_text("gates:\n  field_range_ut: [20, 80]\n")
    assert config.load(str(f), environ={}).gates.field_range_ut == (20.0, 80.0)


def test_a_directory_or_an_unreadable_file_as_config_is_named(tmp_path):
    with pytest.raises(ConfigError) as exc:
        config.load(str(tmp_path), environ={})
    _named(exc, str(tmp_path), "cannot read")
    with pytest.raises(ConfigError) as exc:  # unreadable even for root
        config.load("/proc/self/mem", environ={})
    _named(exc, "/proc/self/mem", "cannot read")


@pytest.mark.parametrize(
    "env, words",
    [
        ({"MAGCAL_PORT": "/dev/ttyACM0", "MAGCAL_PORT__X": "1"}, ["MAGCAL_PORT__X", "port"]),
        ({"MAGCAL_GATES__FIELD_RANGE_UT": "[1,2,3]"}, ["MAGCAL_GATES__FIELD_RANGE_UT", "2 numbers"]),
        ({"MAGCAL_DAEMON__STATE_EVERY_S": ".nan"}, ["MAGCAL_DAEMON__STATE_EVERY_S", "finite"]),
        ({"MAGCAL_TIMEOUT_S": ".inf"}, ["MAGCAL_TIMEOUT_S", "finite"]),
        ({"MAGCAL_DAEMON__STALL_S": "nan"}, ["MAGCAL_DAEMON__STALL_S", "number"]),
        ({"MAGCAL_GATES": "3"}, ["MAGCAL_GATES", "mapping"]),
        ({"MAGCAL_": "1"}, ["MAGCAL_", "not a setting name"]),
        ({"MAGCAL_RATE_HZ": "[" * 5000}, ["MAGCAL_RATE_HZ", "not a value"]),
        ({"MAGCAL_DAEMON__RECONNECT_MIN_S": "10", "MAGCAL_DAEMON__RECONNECT_MAX_S": "5"},
         ["reconnect_max_s", "MAGCAL_DAEMON__RECONNECT_MAX_S", "MAGCAL_DAEMON__RECONNECT_MIN_S"]),
    ],
)
def test_a_bad_environment_variable_is_named(env, words):
    with pytest.raises(ConfigError) as exc:
        config.load(environ=env)
    _named(exc, *words)


def test_a_binary_file_named_by_magcal_config_is_named(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_bytes(bytes(range(128, 256)))
    with pytest.raises(ConfigError) as exc:
        config.load(environ={"MAGCAL_CONFIG": str(f)})
    _named(exc, "MAGCAL_CONFIG", str(f), "UTF-8")


def test_a_text_setting_takes_the_variable_as_it_is():
    assert config.load(environ={"MAGCAL_PORT": "yes"}).port == "yes"  # not YAML's True
    assert config.load(environ={"MAGCAL_PORT": "0x10"}).port == "0x10"


@pytest.mark.parametrize("key", ["timeout_s"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1.0, 0.0])
def test_a_command_line_value_out_of_bounds_is_named(key, value):
    with pytest.raises(ConfigError) as exc:
        config.load(overrides={key: value}, environ={})
    _named(exc, key, "command line")


def test_a_baud_rate_in_the_config_does_not_break_a_port_without_one(tmp_path, capsys):
    """baud is a serial-port setting: sim:// ignores it; --baud with sim:// is refused by name."""
    from magcal.cli import main

    cfg = tmp_path / "c.yaml"
    cfg.write_text("baud: 9600\n")
    cal = tmp_path / "cal.json"
    cal.write_text('{"offset_ut": [1, 2, 3], "field_ut": 48, "evidence": {"n_used": 1000, "coverage": 0.8, "condition": 5.0, "rms_ut": 0.4, "offset_sigma_ut": [0.02, 0.02, 0.02]}}')
    port = f"sim://?eeprom={tmp_path}/e.bin"
    assert main(["write", str(cal), "--port", port, "--config", str(cfg)]) == 0
    capsys.readouterr()
    assert main(["write", str(cal), "--port", port, "--baud", "9600"]) == 2
    assert "--baud applies to serial ports" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["record", "--port", "sim://?pace=0", "-o", "{tmp}/r.cap", "--seconds", "nan"],
    ["record", "--port", "sim://?pace=0", "-o", "{tmp}/r.cap", "--seconds", "inf"],
    ["calibrate", "--port", "sim://?pace=0", "--timeout", "nan"],
    ["stream", "--port", "sim://?pace=0", "--seconds", "inf"],
    ["simulate", "-o", "{tmp}/s.csv", "--seconds", "nan"],
    ["simulate", "-o", "{tmp}/s.csv", "--noise-ut", "inf"],
    ["fit", "{tmp}/none.csv", "--noise-ut", "nan"],
])
def test_nan_and_infinity_are_refused_for_every_number_option(tmp_path, capsys, argv):
    """``record --seconds nan`` hung; ``state_every_s: .nan`` kept the state from ever being saved."""
    from magcal.cli import main

    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"argument {argv[-2]}" in err and "finite" in err


def test_the_daemon_keeps_its_state_in_the_users_state_directory_by_default(tmp_path, monkeypatch):
    """No daemon.state_dir, or an empty one: $XDG_STATE_HOME/magcal (where emu:// keeps its
    EEPROM too), not a fixed ~/.local/state that ignores the user's setting."""
    from magcal.app.daemon import Daemon
    from magcal.recordings.state import state_directory

    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    f = tmp_path / "c.yaml"
    f.write_text('daemon:\n  state_dir: ""\n')
    for s in (config.load(environ={}), config.load(str(f), environ={})):
        assert Daemon(s).state_dir == tmp_path / "xdg" / "magcal"
        assert state_directory(s.daemon.state_dir, create=False) == tmp_path / "xdg" / "magcal"
    f.write_text(f'daemon:\n  state_dir: "{tmp_path / "mine"}"\n')
    assert Daemon(config.load(str(f), environ={})).state_dir == tmp_path / "mine"  # a named one is kept


def test_daemon_keep_is_one_of_its_choices_from_file_environment_or_command_line(tmp_path):
    """``daemon.keep`` is read into its typed choice; anything else names the key, the choices and
    where it was set."""
    assert config.load(None, {}, environ={}).daemon.keep is config.Keep.TRACKER
    assert config.load(None, {}, environ={"MAGCAL_DAEMON__KEEP": "alarm"}).daemon.keep is config.Keep.ALARM
    f = tmp_path / "c.yaml"
    f.write_text("daemon:\n  keep: alarm\n")
    assert config.load(str(f), {}, environ={}).daemon.keep is config.Keep.ALARM
    assert config.to_dict(config.load(str(f), {}, environ={}))["daemon"]["keep"] == "alarm"
    with pytest.raises(ConfigError, match=r"MAGCAL_DAEMON__KEEP: daemon\.keep must be tracker or alarm, got .often."):
        config.load(None, {}, environ={"MAGCAL_DAEMON__KEEP": "often"})
    with pytest.raises(ConfigError, match=r"daemon\.keep must be tracker or alarm, got 3"):
        config.load(None, {"daemon": {"keep": 3}}, environ={})
