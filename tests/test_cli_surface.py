"""The command line as a new user meets it: which device, which options, which exit status,
which JSON. Run as a user runs it (a subprocess) wherever the environment matters."""

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from cli_inproc import run_magcal

from magcal.cli import COMMANDS, build_parser, main
from magcal.cli.exits import MEANING, Exit
from magcal.cli.ports import Candidate, choose_port
from magcal.core.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
DEVICE_COMMANDS = ("calibrate", "write", "run", "show", "stream", "record")


def magcal(*argv, env=None, cwd=None, timeout=120, stdin=subprocess.DEVNULL):
    """Run ``magcal`` as a user would, in a clean environment (no MAGCAL_* of the caller's)."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("MAGCAL_")}
    base["PYTHONPATH"] = str(REPO)
    base.update(env or {})
    return subprocess.run([sys.executable, "-m", "magcal", *argv], capture_output=True, text=True,
                          env=base, cwd=cwd, timeout=timeout, stdin=stdin)


@pytest.fixture
def in_process(monkeypatch):
    """``magcal`` run in this process, for what does not depend on the environment (no MAGCAL_*
    of the caller's, as with ``magcal``): no interpreter to start, nothing imported again."""
    for name in [k for k in os.environ if k.startswith("MAGCAL_")]:
        monkeypatch.delenv(name)
    return run_magcal


def subparsers():
    parser = build_parser("all")
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


# -- which device -------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("command", ["calibrate", "show", "record", "run"])
def test_no_port_is_never_the_simulator(tmp_path, command):
    extra = {"record": ["-o", str(tmp_path / "x.cap"), "--seconds", "1"], "run": ["--state-dir", str(tmp_path)]}
    p = magcal(command, *extra.get(command, []), env={"HOME": str(tmp_path)}, cwd=tmp_path)
    assert p.returncode == 2, p.stderr
    assert "no device named" in p.stderr and "--port" in p.stderr and "sim://" in p.stderr
    assert "VERIFIED" not in p.stdout and "connected" not in p.stderr
    assert not (tmp_path / "x.cap").exists()


def test_the_port_comes_from_the_environment_or_the_config_file(tmp_path):
    p = magcal("show", "--json", env={"MAGCAL_PORT": "sim://?speed=0&seed=3"})
    assert p.returncode == 1, p.stderr  # the answer is no: nothing stored
    assert json.loads(p.stdout)["port"] == "sim://?speed=0&seed=3"
    cfg = tmp_path / "m.yaml"
    cfg.write_text('port: "sim://?speed=0&seed=4"\n')
    p = magcal("show", "--json", "--config", str(cfg))
    assert p.returncode == 1 and json.loads(p.stdout)["port"] == "sim://?speed=0&seed=4"
    p = magcal("show", "--json", "--port", "sim://?speed=0&seed=5", env={"MAGCAL_PORT": "sim://?seed=9"})
    assert json.loads(p.stdout)["port"] == "sim://?speed=0&seed=5"  # the command line wins


def test_exactly_one_serial_device_is_used_and_named():
    said = []
    port = choose_port([Candidate("/dev/ttyACM0", "Arduino Uno")], say=said.append)
    assert port == "/dev/ttyACM0" and "/dev/ttyACM0" in said[0] and "Arduino Uno" in said[0]


def test_several_serial_devices_are_listed_not_guessed():
    found = [Candidate("/dev/ttyACM0", "Arduino Uno"), Candidate("/dev/ttyUSB0", "CP2102")]
    with pytest.raises(ConfigError) as exc:
        choose_port(found)
    assert "/dev/ttyACM0" in str(exc.value) and "/dev/ttyUSB0" in str(exc.value) and "--port" in str(exc.value)
    assert choose_port(found, ask=lambda prompt: "/dev/ttyUSB0\n") == "/dev/ttyUSB0"


@pytest.mark.parametrize("command", DEVICE_COMMANDS)
def test_every_device_command_takes_the_same_port_options(command):
    p = subparsers()[command]
    flags = {f for a in p._actions for f in a.option_strings}
    assert {"--port", "--baud", "--dialect", "--config"} <= flags


# -- options ------------------------------------------------------------------------------------


def test_every_option_has_help_and_says_its_default():
    for name, p in subparsers().items():
        for a in p._actions:
            if not a.option_strings or a.help == argparse.SUPPRESS or isinstance(a, argparse._HelpAction):
                continue
            assert a.help, f"{name} {a.option_strings} has no help"
            if a.default not in (None, False):
                text = p.formatter_class("x")._get_help_string(a)
                assert "default" in text, f"{name} {a.option_strings}: default {a.default!r} not shown"


def test_one_option_means_one_thing_everywhere():
    seen = {}
    for name, p in subparsers().items():
        for a in p._actions:
            for flag in a.option_strings:
                if a.help == argparse.SUPPRESS or flag in ("-h", "--help"):
                    continue
                key = (getattr(a.type, "__name__", a.type), a.metavar, tuple(a.choices or ()))
                seen.setdefault(flag, {})[name] = key
    for flag in ("--port", "--baud", "--dialect", "--config", "--json", "--quiet", "--count", "--timeout",
                 "--output", "--state-dir"):
        kinds = set(seen[flag].values())
        assert len(kinds) == 1, f"{flag} differs between commands: {seen[flag]}"
    assert set(seen["--rate"][c] for c in DEVICE_COMMANDS if c in seen["--rate"]) == {("rate_hz", "HZ", ())}
    # the old spellings still work, unlisted
    for old in ("--noise", "--samples", "--stall-s"):
        assert old not in seen


@pytest.mark.parametrize("argv, words", [
    (["fit", "x.csv", "--noise-ut", "-1"], ["--noise-ut", "positive", "-1"]),
    (["calibrate", "--rate", "500"], ["--rate", "1 to 100", "500"]),
    (["simulate", "-o", "x.csv", "--offset-ut", "1,2"], ["--offset-ut", "3 comma-separated", "1,2"]),
    # a field far beyond the sensor's range overflowed to a recording without any field in it
    (["simulate", "-o", "x.csv", "--field-ut", "1e300"], ["--field-ut", "12290", "1e300"]),
    (["record", "--port", "sim://", "-o", "x.cap", "--seconds", "nan"], ["--seconds", "finite", "nan"]),
    (["diagnose", "x.csv", "--alpha", "1.5"], ["--alpha", "between 0 and 1"]),
    (["stream", "--port", "sim://", "--count", "0"], ["--count", "positive whole number"]),
])
def test_a_bad_value_is_a_usage_error_naming_option_rule_and_value(argv, words, tmp_path):
    p = magcal(*argv, cwd=tmp_path)
    assert p.returncode == 2
    assert all(w in p.stderr for w in words), p.stderr
    assert "Traceback" not in p.stderr


def test_old_spellings_still_work(tmp_path):
    out = tmp_path / "s.csv"
    assert main(["simulate", "-o", str(out), "--seconds", "5", "--noise", "0.2", "--offset", "1,2,3", "--json"]) == 0


# -- exit status --------------------------------------------------------------------------------


def test_help_lists_every_command_and_the_exit_status_table():
    p = magcal("--help")
    assert p.returncode == 0
    for name in COMMANDS:
        assert re.search(rf"^\s+{name}\s", p.stdout, re.M), name
    for code, meaning in MEANING.items():
        assert f"{int(code):>3}  {meaning}" in p.stdout
    sub = magcal("calibrate", "--help")
    assert "exit status:" in sub.stdout and MEANING[Exit.GATE] in sub.stdout


def test_readme_gives_the_same_exit_status_table():
    readme = (REPO / "README.md").read_text()
    for code, meaning in MEANING.items():
        assert re.search(rf"^\| {int(code)} \| {re.escape(meaning)} \|$", readme, re.M), f"README lacks exit {int(code)}"


@pytest.mark.slow
def test_each_exit_status_means_one_thing(tmp_path):
    assert magcal("fit", "--model", "round", "x.csv").returncode == Exit.USAGE
    assert magcal("show", "--port", str(tmp_path / "ttyNONE")).returncode == Exit.DEVICE
    assert magcal("fit", str(tmp_path / "missing.csv")).returncode == Exit.INPUT
    cap = tmp_path / "run.cap"
    assert magcal("record", "--port", "sim://?speed=0&seed=6", "-o", str(cap), "--count", "2500").returncode == 0
    replay = magcal("calibrate", "--port", f"replay://{cap}")
    assert replay.returncode == Exit.WRITE and "read-only" in replay.stdout  # a fit, but nothing written
    assert magcal("calibrate", "--port", f"replay://{cap}", "--no-write").returncode == Exit.OK
    flat = magcal("calibrate", "--port", "sim://?speed=0&motion=yaw", "--timeout", "1", "--no-write")
    assert flat.returncode == Exit.GATE and "min_coverage" in flat.stdout


# -- JSON ---------------------------------------------------------------------------------------


def _keys(obj, path=""):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield path + k, k
            yield from _keys(v, path + k + ".")
    elif isinstance(obj, list):
        for v in obj:
            yield from _keys(v, path)


@pytest.mark.slow
def test_every_command_prints_one_versioned_json_shape_with_one_vocabulary(tmp_path, in_process):
    magcal = in_process  # what each command prints does not depend on the environment
    sim, cap, csv, js = "sim://?speed=0&seed=2", tmp_path / "r.cap", tmp_path / "r.csv", tmp_path / "f.json"
    eeprom = f"sim://?speed=0&seed=2&eeprom={tmp_path}/e.bin"
    runs = {
        "simulate": ["simulate", "-o", str(csv), "--seconds", "40", "--json"],
        "record": ["record", "--port", sim, "-o", str(cap), "--count", "400", "--json"],
        "fit": ["fit", str(csv), "--json"],
        "diagnose": ["diagnose", str(csv), "--json"],
        "export": ["export", str(cap), "-o", str(tmp_path / "e.csv"), "--json"],
        "calibrate": ["calibrate", "--port", eeprom, "--rate", "20", "--json"],  # ~800 samples, not ~1900
        "write": ["write", str(js), "--port", eeprom, "--json"],
        "show": ["show", "--port", eeprom, "--json"],
        "status": ["status", "--state-dir", str(tmp_path / "nothing"), "--json"],
        "stream": ["stream", "--port", sim, "--count", "3", "--json"],
    }
    for name, argv in runs.items():
        p = magcal(*argv)
        assert p.returncode in (0, 1), f"{name}: {p.stderr}"
        docs = [json.loads(line) for line in p.stdout.splitlines()] if name == "stream" else [json.loads(p.stdout)]
        for d in docs:
            assert d["schema"] == f"magcal.{name}/1", name
            for path, key in _keys(d):
                assert key not in ("samples", "kept", "rms", "quality", "seconds", "identity"), f"{name}: {path}"
                if "rms" in key:
                    assert key.endswith("_ut"), f"{name}: {path} (µT quantities end in _ut)"
        if name == "fit":
            js.write_text(p.stdout)  # `write` takes what `fit --json` printed
    status = json.loads(magcal(*runs["status"]).stdout)
    assert status["running"] is False and status["source"] == "none"


@pytest.mark.slow
def test_calibrate_json_reports_the_rate_it_used(in_process):
    p = in_process("calibrate", "--port", "sim://?speed=0", "--rate", "20", "--no-write", "--json")
    d = json.loads(p.stdout)
    assert p.returncode == 0 and d["rate_hz"] == 20 and d["device"]["rate_hz"] == 20
    assert d["measured_rate_hz"] > 0


# -- the simulated board keeps time ---------------------------------------------------------------


@pytest.mark.slow
def test_sim_runs_in_real_time_unless_asked_not_to(tmp_path):
    p = magcal("record", "--port", "sim://", "--rate", "20", "--seconds", "2", "-o", str(tmp_path / "a.cap"), "--json")
    d = json.loads(p.stdout)
    assert p.returncode == 0 and 30 <= d["n_samples"] <= 50, d  # 2 s at 20 Hz, not minutes of sensor time
    assert d["rate_hz"] == 20
    fast = magcal("record", "--port", "sim://?speed=0", "--count", "3000", "-o", str(tmp_path / "b.cap"), "--json")
    d = json.loads(fast.stdout)
    assert fast.returncode == 0 and d["n_samples"] >= 3000 and d["elapsed_s"] < 20


# -- start-up (the figures are in bench/startup.py; here, what is loaded) ------------------------


def _modules_after(argv, tmp_path):
    script = ("import sys, contextlib, io\nfrom magcal.cli import main\n"
              "with contextlib.redirect_stdout(io.StringIO()):\n"
              "    try:\n        main(sys.argv[1:])\n    except SystemExit:\n        pass\n"
              "print(' '.join(sorted(sys.modules)))")
    p = subprocess.run([sys.executable, "-c", script, *argv], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(REPO)), cwd=tmp_path, timeout=60)
    return set(p.stdout.split())


def test_help_loads_no_command_module_and_no_numpy(tmp_path):
    loaded = _modules_after(["--help"], tmp_path)
    assert not any(m.startswith("magcal.cli.") and m.split(".")[-1] in COMMANDS for m in loaded)
    assert "numpy" not in loaded and "scipy" not in loaded


def test_a_fit_loads_only_its_own_command_and_of_scipy_only_special(tmp_path):
    """The Grubbs test's t quantile comes from scipy.special (magcal.fit.tails); the heavy
    parts (stats, optimize, linalg) stay unloaded."""
    assert main(["simulate", "-o", str(tmp_path / "s.csv"), "--seconds", "6.48"]) == 0
    loaded = _modules_after(["fit", str(tmp_path / "s.csv")], tmp_path)
    assert "magcal.cli.fit" in loaded and "magcal.cli.calibrate" not in loaded
    assert not any(m.startswith(("scipy.stats", "scipy.optimize", "scipy.linalg")) for m in loaded)


# -- emu:// remembers, as a board does ------------------------------------------------------------


@pytest.mark.slow
def test_emu_keeps_its_eeprom_in_the_users_state_directory(tmp_path):
    from firmware_support import require_firmware

    require_firmware()
    env = {"XDG_STATE_HOME": str(tmp_path / "state")}
    # at 20 Hz: the same turning in ~750 samples instead of ~1 750 (where the EEPROM is kept
    # does not depend on the rate)
    cal = magcal("calibrate", "--port", "emu://?seed=3", "--rate", "20", "--json", env=env, timeout=300)
    said = json.loads(cal.stdout) if cal.stdout.strip().startswith("{") else {}
    why = {k: said.get(k) for k in ("status", "failure", "failed_gate", "message", "n_samples", "coverage")}
    assert cal.returncode == 0 and said["verified"], (cal.returncode, why, cal.stderr)
    shown = magcal("show", "--port", "emu://?seed=3", "--json", env=env)  # a new process, a new harness
    d = json.loads(shown.stdout)
    assert shown.returncode == 0 and d["calibration"]["offset_ut"] == pytest.approx(
        json.loads(cal.stdout)["calibration"]["offset_ut"], abs=0.01)
    assert d["stored_in"].startswith(str(tmp_path / "state" / "magcal" / "emu"))
    # told otherwise: a file of the user's choosing, or none kept at all
    assert magcal("show", "--port", "emu://?seed=3&eeprom=none", env=env).returncode == 1
    assert magcal("show", "--port", f"emu://?seed=3&eeprom={tmp_path}/own.bin", env=env).returncode == 1


@pytest.mark.slow
def test_a_short_timeout_names_the_gate_it_stopped_on_or_calibrates(in_process):
    for _ in range(3):
        p = in_process("calibrate", "--port", "sim://?pace=0", "--timeout", "0.2", "--no-write")
        assert p.returncode in (Exit.OK, Exit.GATE), p.stderr
        if p.returncode == Exit.GATE:
            failing = re.search(r"failing: ([a-z_, ]+) \(", p.stdout)
            assert failing and failing.group(1).strip(), p.stdout  # never "failing: none ()"
