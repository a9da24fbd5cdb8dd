"""The state file: what is saved is what loads; a torn, altered or foreign file is refused with
a StateError naming the defect, and the previous good state is used instead."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.core.errors import StateError
from magcal.core.sample import Sample
from magcal.logic.session import Session
from magcal.recordings.state import StateFiles, decode_state, encode_state
from magcal.sim.physics import demo_scenario

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**53, 2**53) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=20,
)


@settings(max_examples=100, deadline=None)
@given(st.dictionaries(st.text(max_size=8), json_values, max_size=6))
def test_round_trip(payload):
    assert decode_state(encode_state(payload)) == payload


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_every_truncation_is_refused(data):
    blob = encode_state({"samples": 1234, "offset_ut": [1.5, -2.25, 3.0], "note": "x" * 20})
    cut = data.draw(st.integers(0, len(blob) - 2))  # the trailing newline is not part of the JSON
    with pytest.raises(StateError):
        decode_state(blob[:cut])


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_every_single_byte_change_is_refused_or_harmless(data):
    payload = {"samples": 1234, "offset_ut": [1.5, -2.25, 3.0]}
    blob = bytearray(encode_state(payload))
    i = data.draw(st.integers(0, len(blob) - 2))
    b = data.draw(st.integers(0, 255).filter(lambda x: x != blob[i]))
    blob[i] = b
    try:
        got = decode_state(bytes(blob))
    except StateError:
        return
    assert got == payload  # only a change JSON ignores (whitespace-like) may pass


def test_wrong_version_and_format_are_named():
    doc = json.loads(encode_state({"a": 1}))
    doc["version"] = 99
    with pytest.raises(StateError, match="version 99"):
        decode_state(json.dumps(doc).encode())
    with pytest.raises(StateError, match="not a magcal state"):
        decode_state(b'{"hello": 1}')
    with pytest.raises(StateError, match="empty"):
        decode_state(b"")


def test_store_falls_back_to_previous_good_file(tmp_path):
    store = StateFiles(tmp_path)
    assert store.load() is None
    store.save({"generation": 1})
    store.save({"generation": 2})
    assert store.load() == {"generation": 2}
    # a crash that left a torn current file (e.g. a filesystem without atomic rename)
    data = store.current.read_bytes()
    store.current.write_bytes(data[: len(data) // 2])
    assert store.load() == {"generation": 1}
    assert "refusing state.json" in store.last_load_note
    # the torn file is never promoted to "previous"
    store.save({"generation": 3})
    assert store.load() == {"generation": 3}
    assert decode_state(store.previous.read_bytes()) == {"generation": 1}


def test_store_with_no_valid_file_raises(tmp_path):
    store = StateFiles(tmp_path)
    store.current.write_bytes(b'{"format": "magcal-state", "vers')
    with pytest.raises(StateError, match="no valid state"):
        store.load()


def test_nan_is_refused_when_saving(tmp_path):
    with pytest.raises(StateError, match="JSON"):
        StateFiles(tmp_path).save({"x": float("nan")})


def test_collecting_session_resumes_exactly():
    sc = demo_scenario(2)
    run = sc.simulate(900, 50.0)
    samples = [Sample(seq=i, t_s=float(t), field_ut=tuple(m)) for i, (t, m) in
               enumerate(zip(run.series.t_s, run.series.field_ut))]
    a = Session()
    a.add_many(samples[:500])
    b = Session.from_state(json.loads(json.dumps(a.to_state())))
    a.add_many(samples[500:])
    b.add_many(samples[500:])
    assert a.counters == b.counters
    assert a.accumulator.n == b.accumulator.n == 900
    assert np.array_equal(a.kept.field_ut, b.kept.field_ut)
    assert a.progress() == b.progress()
    assert [g.to_dict() for g in a.live_gates()] == [g.to_dict() for g in b.live_gates()]


# -- the state directory and the umask -----------------------------------------------------------
import os  # noqa: E402

from magcal.cli import main  # noqa: E402


def _main(argv) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # a usage error found while parsing the options
        return exc.code


@pytest.mark.parametrize("command", ["run", "status"])
def test_a_state_dir_that_is_a_file_is_named(tmp_path, capsys, command):
    f = tmp_path / "afile"
    f.write_text("x")
    for d in (f, f / "sub"):
        argv = [command, "--state-dir", str(d)] + (["--port", "sim://?pace=0", "--count", "10"] if command == "run" else [])
        assert _main(argv) == 2
        err = capsys.readouterr().err
        assert str(d) in err and ("not a directory" in err or "does not exist" in err) and "Traceback" not in err


class _Unprivileged:
    """Root may write anywhere: as root, act as the unprivileged user 'nobody' for a while."""

    def __enter__(self):
        self.root = os.geteuid() == 0
        if self.root:
            os.setegid(65534)
            os.seteuid(65534)

    def __exit__(self, *exc):
        if self.root:
            os.seteuid(0)
            os.setegid(0)


def test_a_state_dir_this_user_cannot_write_is_named(capsys):
    import shutil
    import tempfile

    base = tempfile.mkdtemp(prefix="magcal-ro-")
    # the same command once as this user first: what it imports is then loaded (the
    # unprivileged user may not read this Python's library folders)
    assert _main(["run", "--port", "sim://?pace=0", "--count", "5", "--state-dir", os.path.join(base, "ok")]) == 0
    capsys.readouterr()
    try:
        os.chmod(base, 0o755)
        ro = os.path.join(base, "ro")
        os.mkdir(ro, 0o555)
        os.chmod(ro, 0o555)
        for d, words in ((ro, "not writable by this user"), (os.path.join(ro, "sub"), "cannot be created")):
            with _Unprivileged():
                code = _main(["run", "--port", "sim://?pace=0", "--count", "10", "--state-dir", d])
            err = capsys.readouterr().err
            assert code == 2 and f"state directory {d}: {words}" in err and "Traceback" not in err, err
    finally:
        shutil.rmtree(base)


def test_state_files_honour_a_restrictive_umask(tmp_path):
    old = os.umask(0o077)
    try:
        store = StateFiles(tmp_path / "s")
        store.save({"a": 1})
        store.save({"a": 2})  # the previous one is kept as state.prev.json
    finally:
        os.umask(old)
    for name in ("state.json", "state.prev.json"):
        assert (tmp_path / "s" / name).stat().st_mode & 0o777 == 0o600
    store.save({"a": 3})  # under the usual umask 022: 0644, as before
    assert (tmp_path / "s" / "state.json").stat().st_mode & 0o077 == (0o644 & ~old) & 0o077
