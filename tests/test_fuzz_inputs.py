"""Every input surface, fuzzed: whatever a user (or a damaged file) hands magcal becomes a value
or a named error — one line that names the input — and never a traceback.

Surfaces: config documents, environment maps (MAGCAL_*), command-line option vectors of every
command, capture files, any file given as a recording, JSON results given to ``write``, and
stored records (the device's calibration record, the host store's files, the daemon's state
file). Each test is bounded to a few seconds of CPU (CI runs them all)."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from magcal.app import config
from magcal.app.load import load_series
from magcal.cli import COMMANDS, _load, main
from magcal.core.calibration import RecordState
from magcal.core.errors import ConfigError, InputError, MagcalError
from magcal.recordings.capture import CaptureWriter, make_header
from magcal.wire.protocol import RECORD_FIELDS, encode_line, record_crc, stored_record

FUZZ = settings(max_examples=120, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def one_line_naming(text: str, *names: str) -> None:
    assert text and "\n" not in text.strip() and "Traceback" not in text, text
    assert any(n in text for n in names), (text, names)


# -- values a hostile user types --------------------------------------------------------------------
NASTY_TEXT = ["nan", "NaN", "inf", "-inf", "1e999", "-1", "0", "-0", "1e9", "1e308", "", " ", "abc", "0,0,0",
              "1,2", "1,2,3,4", "nan,0,0", "0x10", "1_000", "٣", "9" * 400, "-" * 3, "/proc/x", "/dev/null",
              "~", "a\tb", "ümlaut", "[1,2]", "{a: 1}", "!!python/object:os.system", "*ref", "&a [*a]"]
scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(NASTY_TEXT), st.text(max_size=30),
)
KNOWN_KEYS = ["port", "dialect", "baud", "rate_hz", "model", "timeout_s", "write", "gates", "daemon",
              "min_samples", "min_coverage", "max_rms_ut", "field_range_ut", "max_offset_ut", "max_offset_sigma_ut",
              "max_condition", "state_dir", "recalibrate", "monitor_window", "monitor_alpha", "reconnect_min_s",
              "reconnect_max_s", "capture_max_bytes", "state_every_s", "socket", "stall_s"]
keys = st.one_of(st.sampled_from(KNOWN_KEYS), st.text(max_size=10), st.integers(-5, 5), st.none(), st.booleans())
documents = st.recursive(scalars, lambda inner: st.lists(inner, max_size=5) | st.dictionaries(keys, inner, max_size=6),
                         max_leaves=25)


# -- config documents ---------------------------------------------------------------------------------
def _yaml(doc) -> str:
    import yaml

    try:
        return yaml.safe_dump(doc, allow_unicode=True)
    except (yaml.YAMLError, TypeError, ValueError, RecursionError):
        return repr(doc)


@FUZZ
@pytest.mark.slow
@given(st.one_of(documents.map(_yaml).map(lambda t: t.encode("utf-8")), st.binary(max_size=300),
                 st.text(max_size=300).map(lambda t: t.encode("utf-8", "surrogatepass"))))
def test_a_config_document_is_settings_or_a_named_error(tmp_path, blob):
    path = tmp_path / "c.yaml"
    path.write_bytes(blob)
    try:
        s = config.load(str(path), environ={})
    except ConfigError as exc:
        one_line_naming(str(exc), str(path))
        return
    s.check()  # what loads is within every declared bound


# -- environment maps ---------------------------------------------------------------------------------
ENV_NAMES = [f"MAGCAL_{p}" for p in ("PORT", "BAUD", "RATE_HZ", "TIMEOUT_S", "WRITE", "MODEL", "DIALECT",
                                     "GATES", "GATES__FIELD_RANGE_UT", "GATES__MIN_SAMPLES", "GATES__MIN_COVERAGE",
                                     "DAEMON__STATE_EVERY_S", "DAEMON__STALL_S", "DAEMON__STATE_DIR", "PORT__X",
                                     "", "_", "GATES__", "daemon__socket", "COLOUR")]
env_values = st.one_of(st.sampled_from(NASTY_TEXT), st.text(max_size=40).filter(lambda t: "\0" not in t),
                       documents.map(_yaml))


@FUZZ
@given(st.dictionaries(st.sampled_from(ENV_NAMES), env_values, max_size=5))
def test_an_environment_is_settings_or_an_error_naming_the_variable(env):
    try:
        s = config.load(environ=env)
    except ConfigError as exc:
        one_line_naming(str(exc), *env)
        return
    s.check()


# -- command-line option vectors ----------------------------------------------------------------------
def _options(command: str) -> list[argparse.Action]:
    p = argparse.ArgumentParser(prog=f"magcal {command}")
    _load(command).add_arguments(p)
    return [a for a in p._actions if a.option_strings and a.dest != "help"]


def _value_for(draw, action, files: dict) -> list[str]:
    if action.nargs == 0:
        return []
    if action.choices:
        return [draw(st.sampled_from([*map(str, action.choices), "bogus"]))]
    return [draw(st.sampled_from([*NASTY_TEXT, "1", "2.5", "0.5", "3", files["csv"], files["dir"], files["cap"]]))]


# ports that fail fast, or finish fast: a command run with a valid vector must end by itself (the
# daemon retries a port that is missing — it may be plugged in later — so it gets only ports that
# are refused at once or end)
PORTS = ["bogus://x", "sim://?seed=x", "/dev/magcal-no-such-port", "replay:///no/such/file.cap", "i2c:x", ""]
DAEMON_PORTS = ["sim://?seed=x", "sim://?bogus=1", ""]


def _ports(command: str, files: dict) -> list[str]:
    return [*(DAEMON_PORTS if command == "run" else PORTS), f"replay://{files['cap']}?pace=0"]


@st.composite
def argv_of(draw, command: str, files: dict):
    argv = [command]
    if command in ("fit", "diagnose", "export", "write"):
        argv.append(draw(st.sampled_from([files["csv"], files["cap"], files["json"], files["bin"], files["dir"],
                                          "/no/such/file", "-" if command == "write" else files["csv"]])))
    options = _options(command)  # none at the top of a command made of subcommands (service, firmware)
    drawn = draw(st.lists(st.sampled_from(options), max_size=4, unique_by=lambda a: a.dest)) if options else []
    for action in drawn:
        flag = draw(st.sampled_from(action.option_strings))
        if action.dest == "port":
            argv += [flag, draw(st.sampled_from(_ports(command, files)))]
            continue
        argv += [flag, *_value_for(draw, action, files)]
    if command in ("calibrate", "record", "stream", "run", "show", "write") and "--port" not in argv:
        argv += ["--port", draw(st.sampled_from(_ports(command, files)))]
    if command in ("record", "simulate") and not {"-o", "--output"} & set(argv):
        argv += ["-o", files["out"]]
    if command == "status" and "--state-dir" not in argv:
        argv += ["--state-dir", files["state"]]
    return argv


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return make_files(tmp_path_factory.mktemp("fuzzcli"))


def make_files(d) -> dict:
    """Small inputs for the option vectors: a table, a capture, a calibration, a binary file."""
    rng = np.random.default_rng(1)
    u = rng.normal(size=(200, 3))
    m = 40 * u / np.linalg.norm(u, axis=1, keepdims=True) + [10, -20, 5]
    (d / "s.csv").write_text("t,mx,my,mz\n" + "".join(f"{i * 0.02},{a},{b},{c}\n" for i, (a, b, c) in enumerate(m)))
    with CaptureWriter(d / "s.cap", make_header("sim://", None)) as w:
        w.append(b"".join(encode_line("S", (i + 1, 10 * i, *np.round(v / 0.3).astype(int), 0, 0))
                          for i, v in enumerate(m)), t_rx_s=0.0)
    (d / "r.json").write_text(json.dumps({"offset_ut": [1, 2, 3], "field_ut": 48}))
    (d / "b.bin").write_bytes(bytes(range(256)) * 4)
    (d / "dir").mkdir()
    (d / "scratch").mkdir()
    return {"scratch": str(d / "scratch"), "csv": str(d / "s.csv"), "cap": str(d / "s.cap"), "json": str(d / "r.json"), "bin": str(d / "b.bin"),
            "dir": str(d / "dir"), "out": str(d / "out.csv"), "state": str(d / "state")}


def _run_main(argv) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # argparse: a usage error, already printed
        return exc.code


@pytest.mark.slow
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_option_vector_ends_in_a_documented_status_and_a_named_error(command, files, capsys, monkeypatch):
    from magcal.cli.exits import Exit

    monkeypatch.setenv("MAGCAL_STORE_DIR", files["state"] + "-store")
    # a drawn word may be taken as an output path: let it land in a scratch folder, not the checkout
    monkeypatch.chdir(files["scratch"])
    for k in [k for k in os.environ if k.startswith("MAGCAL_") and k != "MAGCAL_STORE_DIR"]:
        monkeypatch.delenv(k)
    documented = {int(c) for c in Exit}

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.data())
    def check(data):
        argv = data.draw(argv_of(command, files))
        capsys.readouterr()
        code = _run_main(argv)
        err = capsys.readouterr().err
        assert code in documented, (argv, code, err)
        assert "Traceback" not in err, (argv, err)
        if code in (Exit.USAGE, Exit.DEVICE, Exit.INPUT):  # an error: its last line says what, by name
            last = err.strip().splitlines()[-1] if err.strip() else ""
            assert last.startswith(f"magcal {command}: ") or last.startswith("magcal: "), (argv, err)

    check()


# -- capture files and any file as a recording ------------------------------------------------------------
def _lines(rng_seed: int, n: int) -> list[bytes]:
    rng = np.random.default_rng(rng_seed)
    out = [encode_line("H", (0, 1, "0.1.0", "68", "48", 176, 178, 166, 100))]
    for i in range(n):
        raw = rng.integers(-300, 300, 3)
        kind = "U" if rng.random() < 0.1 else "S"
        out.append(encode_line(kind, (int(rng.integers(0, 65536)) if rng.random() < 0.05 else i + 1, 10 * i,
                                      *raw.tolist(), 0, -3345)))
    return out


@st.composite
def captures(draw):
    header = draw(st.sampled_from([
        json.dumps(make_header("sim://", None)).encode(),
        b'{"format": "magcal-capture", "version": 2}',
        b'{"format": "magcal-capture", "version": 1, "x": "' + b"a" * 70_000 + b'"}',
        b'{"format": "magcal-capture", "version": 1, "dialect": "auto"}',
        b'{"format": "magcal-capture", "version": 1, "dialect": "zzz"}',
        b'{"format": "magcal-capture", "version": ' + b"[" * 3000 + b"]" * 3000 + b"}",
    ]))
    body = b"".join(_lines(draw(st.integers(0, 99)), draw(st.integers(0, 60))))
    chunks, i = [], 0
    while i < len(body):
        k = draw(st.integers(1, 200))
        chunks.append(b"K" + struct.pack("<dI", 0.01 * len(chunks), len(body[i:i + k])) + body[i:i + k])
        i += k
    blob = bytearray(header + b"\n" + b"".join(chunks))
    for _ in range(draw(st.integers(0, 6))):  # damage: flipped bytes, a cut, inserted junk
        how = draw(st.sampled_from(["flip", "cut", "junk"]))
        if not blob:
            break
        at = draw(st.integers(0, len(blob) - 1))
        if how == "flip":
            blob[at] ^= draw(st.integers(1, 255))
        elif how == "cut":
            del blob[at:]
        else:
            blob[at:at] = draw(st.binary(min_size=1, max_size=40))
    return bytes(blob)


@FUZZ
@given(captures())
def test_a_capture_is_samples_or_a_named_error(tmp_path, blob):
    path = tmp_path / "x.cap"
    path.write_bytes(blob)
    try:
        s = load_series(path)
    except InputError as exc:
        one_line_naming(str(exc), str(path))
        return
    assert all(isinstance(v, int) and v >= 0 for v in s.reading.values())
    assert "calibrated" not in s.channels  # U lines are never in a raw series


@FUZZ
@given(st.one_of(st.binary(max_size=2000), st.text(max_size=2000).map(lambda t: t.encode("utf-8", "surrogatepass")),
                 st.lists(st.sampled_from([b"mx,my,mz\n", b"1,2,3\n", b"Raw:1,2,3,4,5,6,7,8,9\n", b"$S,1,2*00\n",
                                           b"nan,inf,1\n", b"\xef\xbb\xbf", b"\0", b"\r", b"1;2;3\n", b"\"1\",2,3\n"]),
                          max_size=40).map(b"".join)))
def test_any_file_given_as_a_recording_is_read_or_named(tmp_path, blob):
    path = tmp_path / "rec.txt"
    path.write_bytes(blob)
    try:
        load_series(path)
    except InputError as exc:
        one_line_naming(str(exc), str(path))


# -- JSON results given to write ------------------------------------------------------------------------
json_docs = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**20), 10**20) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
        st.sampled_from(["offset_ut", "field_ut", "soft_iron", "calibration", "fits", "rms_ut", "uncertainty",
                         "n_used", "coverage", "coef_ut_per_unit", "reference", "temp_c", "t_s", "quality"]),
        inner, max_size=5),
    max_leaves=30)


@FUZZ
@given(st.one_of(json_docs.map(json.dumps), st.sampled_from([
    "[" * 5000, '{"calibration": ' * 3000, "", "nul\0l", '{"offset_ut": [1, 2, 3], "field_ut": Infinity}',
    '{"offset_ut": [NaN, 2, 3], "field_ut": 48}', '{"offset_ut": [1, 2, 3], "field_ut": 48, "rms_ut": -Infinity}'])))
def test_a_json_result_is_a_calibration_with_its_evidence_or_a_named_error(tmp_path, text):
    from magcal.cli.write import _read, calibration_from_json, evidence_from_json
    from magcal.logic.gates import Gates, clear_for_write

    path = tmp_path / "r.json"
    path.write_text(text)
    try:
        obj = _read(str(path))
        cal, _ = calibration_from_json(obj, str(path))
        clear_for_write(Gates(), evidence_from_json(obj, cal, str(path)))
    except InputError as exc:
        one_line_naming(str(exc), str(path))


# -- stored records -------------------------------------------------------------------------------------
int32 = st.integers(-(2**31), 2**31 - 1)


@FUZZ
@given(st.tuples(st.sampled_from([1, 1, 1, 0, 2]), *[int32] * (RECORD_FIELDS - 1)),
       st.sampled_from(["OK", "OK", "BLANK", "CORRUPT"]), st.booleans())
def test_a_device_record_is_a_calibration_or_a_named_state(values, status, crc_ok):
    crc = record_crc(values) if crc_ok else (record_crc(values) + 1) % 65536
    r = stored_record(status, values, crc)
    assert (r.calibration is not None) == (r.state is RecordState.OK)
    assert r.state in (RecordState.OK, RecordState.NONE) or r.problem


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@pytest.mark.slow
@given(st.one_of(st.binary(min_size=75, max_size=75),
                 st.tuples(st.sampled_from([1, 2]), *[int32] * (RECORD_FIELDS - 1)).map(
                     lambda v: bytes([0x4D]) + struct.pack("<18i", *v) + struct.pack("<H", record_crc(v)))))
def test_show_on_any_eeprom_is_a_calibration_or_a_named_record_state(tmp_path, capsys, record):
    ee = tmp_path / "e.bin"
    ee.write_bytes(record + b"\xff" * (1024 - len(record)))
    capsys.readouterr()
    code = main(["show", "--port", f"sim://?pace=0&eeprom={ee}", "--json"])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    if code == 5:  # a record of values so long that its line exceeds the protocol's 120 bytes
        one_line_naming(err.strip(), "overlong lines")
        return
    assert code in (0, 1)
    d = json.loads(out)
    assert (d["calibration"] is not None) == (d["record"]["state"] == "ok")


def _digest(body: dict) -> str:
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(canon.encode("ascii")).hexdigest()


@pytest.mark.slow
@FUZZ
@given(json_docs, st.booleans())
def test_a_host_store_file_is_a_calibration_or_a_named_record_state(tmp_path, calib, sign):
    """A store file whose checksum holds (recomputed, as a forger would) but anything inside."""
    from magcal.core.events import Identity
    from magcal.recordings.store import FORMAT, VERSION, CalibrationStore, device_key

    ident = Identity(transport="i2c", asa=(176, 178, 166), extra={"bus": "/dev/i2c-1", "address": 0x68})
    body = {"format": FORMAT, "version": VERSION, "key": device_key(ident), "device": ident.to_dict(),
            "saved_at": "2026-01-01T00:00:00Z", "calibration": calib}
    if sign:
        body["sha256"] = _digest(body)
    store = CalibrationStore(tmp_path)
    store.path_for(ident).write_text(json.dumps(body))
    r = store.stored(ident)
    assert (r.calibration is not None) == (r.state is RecordState.OK)
    if r.state is not RecordState.OK:
        one_line_naming(r.problem, str(store.path_for(ident)))


@pytest.mark.slow
@FUZZ
@given(st.dictionaries(st.sampled_from(["kind", "generation", "saved_utc", "status", "resume"]), json_docs, max_size=5))
def test_a_state_file_that_checks_out_is_status_or_a_named_error(tmp_path, capsys, payload):
    """``magcal status`` on a state file with a valid checksum and any payload."""
    from magcal.recordings.state import StateFiles

    StateFiles(tmp_path).save(payload)
    for json_out in ([], ["--json"]):
        capsys.readouterr()
        code = _run_main(["status", "--state-dir", str(tmp_path), *json_out])
        out, err = capsys.readouterr()
        assert code in (0, 1, 6) and "Traceback" not in err, err
        if code == 6:
            one_line_naming(err.strip(), str(tmp_path))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.dictionaries(st.sampled_from(["kind", "generation", "saved_utc", "status", "resume"]), json_docs, max_size=5))
def test_a_daemon_resumes_from_any_state_file_or_starts_fresh(tmp_path, payload):
    from magcal.app.daemon import Daemon, Decision
    from magcal.recordings.state import StateFiles

    assume(payload)
    StateFiles(tmp_path / "s").save(payload)
    d = Daemon(config.load(overrides={"port": "sim://?pace=0"}, environ={}), state_dir=tmp_path / "s")
    d.resume()
    assert {Decision.RESUMED, Decision.STATE_UNUSABLE, Decision.STATE_REFUSED, Decision.NO_STATE,
            Decision.STATE_OTHER_PORT} & set(d.journal.decisions())


def test_errors_are_magcal_errors():
    """The fuzz tests above accept only magcal's own named errors: the families they catch."""
    assert issubclass(ConfigError, MagcalError) and issubclass(InputError, MagcalError)


def test_export_of_a_missing_file_over_an_existing_output_names_the_file(tmp_path, capsys):
    """Found by the option fuzz: ``export /no/such/file -o EXISTING`` was a FileNotFoundError."""
    from magcal.cli.exits import Exit

    (tmp_path / "out.csv").write_text("x\n")
    code = _run_main(["export", str(tmp_path / "missing.cap"), "-o", str(tmp_path / "out.csv")])
    err = capsys.readouterr().err
    assert code == Exit.INPUT and "Traceback" not in err
    one_line_naming(err.strip(), "missing.cap")
