"""The edges of the second hardening pass, each a named error with its documented exit status
(or, where the input is fine, taken as meant)."""

import os
import signal

import pytest

from magcal.app import config
from magcal.app.daemon import Daemon, Decision
from magcal.cli import main
from magcal.cli.run import EarlyHangup
from magcal.core.errors import ConfigError
from magcal.recordings.state import StateFiles

HUGE = "9" * 5000


def test_a_5000_digit_integer_in_the_environment_is_a_usage_error(monkeypatch, capsys):
    monkeypatch.setenv("MAGCAL_RATE_HZ", HUGE)
    assert main(["show", "--port", "sim://?pace=0"]) == 2
    assert "MAGCAL_RATE_HZ" in capsys.readouterr().err


def test_a_5000_digit_integer_in_a_config_file_is_named(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"daemon:\n  write_burst: {HUGE}\n")
    with pytest.raises(ConfigError, match="too long"):
        config.load(str(cfg), environ={})


def test_a_number_written_1e_3_is_a_number(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("gates:\n  min_coverage: 5e-1\ndaemon:\n  state_every_s: 1e-3\n")
    s = config.load(str(cfg), environ={"MAGCAL_GATES__MAX_RMS_UT": "2.5E0"})
    assert (s.gates.min_coverage, s.daemon.state_every_s, s.gates.max_rms_ut) == (0.5, 0.001, 2.5)


def test_a_reload_into_a_5000_digit_config_keeps_the_daemon_running(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("rate_hz: 50\n")
    settings = config.load(str(cfg), {"port": "sim://?pace=0", "daemon": {"socket": False}}, environ={})
    d = Daemon(settings, state_dir=tmp_path / "st", config_path=str(cfg), max_samples=1)
    cfg.write_text(f"rate_hz: {HUGE}\n")
    d.reload()
    assert d.journal.decisions()[-1] is Decision.RELOAD_REJECTED and d.settings is settings


def test_a_hangup_before_the_daemon_listens_becomes_a_reload():
    hangup = EarlyHangup()
    try:
        os.kill(os.getpid(), signal.SIGHUP)  # the process lives: it was taken
        assert hangup.pending
        reloads = []
        hangup.hand_to(lambda: reloads.append(1))
        os.kill(os.getpid(), signal.SIGHUP)
        assert reloads == [1, 1]
    finally:
        hangup.restore()


def test_a_state_with_a_good_checksum_and_wrong_content_says_what_is_wrong(tmp_path):
    st = tmp_path / "st"
    StateFiles(st).save({"kind": "magcal-daemon", "generation": 3, "status": {}})
    settings = config.load(None, {"port": "sim://?pace=0", "daemon": {"socket": False}}, environ={})
    d = Daemon(settings, state_dir=st, max_samples=1)
    d.run()
    entry = d.journal.find(Decision.STATE_UNUSABLE)[0]
    assert "no 'resume' entry" in entry["error"]
