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
        ("rate_hz: 500\n", ["rate_hz", "1…100"]),
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


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        config.load(str(tmp_path / "nope.yaml"), environ={})
