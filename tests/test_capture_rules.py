"""A capture is read by the live link's rules: calibrated (U) lines are never raw data, a
re-sent line is taken once, a hello cannot change the chip's identity without a restart, lost
lines are counted as they were lost, and damage to the file's chunk structure is read around
and reported with counts — through the library, the replay device and the commands."""

import json
import re

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.cli import main
from magcal.devices import open_device
from magcal.devices.base import read_to_end
from magcal.recordings.capture import CHUNK_OVERHEAD, CaptureReader, CaptureWriter, make_header
from magcal.wire.protocol import encode_line

N = 3072


@pytest.fixture(scope="module")
def lines(tmp_path_factory):
    """The protocol lines of a real recording of the simulated board: the hello, then N samples."""
    path = tmp_path_factory.mktemp("rec") / "r.cap"
    assert main(["record", "--port", "sim://?seed=4&pace=0", "-o", str(path), "--count", str(N)]) == 0
    data = CaptureReader(path).data()
    out = [ln + b"\n" for ln in data.split(b"\n") if ln.startswith(b"$")]
    assert sum(ln.startswith(b"$S,") for ln in out) == N
    return out


def fields(line: bytes) -> list[str]:
    return line[1 : line.rindex(b"*")].decode().split(",")


def write_capture(path, chunks):
    with CaptureWriter(path, make_header("sim://", None)) as w:
        for i, c in enumerate(chunks):
            w.append(c, t_rx_s=0.01 * i)
    return path


def fit_offset(capsys, path) -> tuple[np.ndarray, dict, str]:
    capsys.readouterr()
    assert main(["fit", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    d = json.loads(out)["fits"][0]
    return np.array(d["calibration"]["offset_ut"]), d["reading"], err


def test_calibrated_lines_are_never_used_as_raw(tmp_path, lines, capsys):
    """Every 4th sample line sent calibrated (U, nT) as a device in calibrated mode does: 768
    of 3072. Read as raw they moved the offset by ~11 µT; they are left out and counted."""
    mixed, k = [], 0
    for ln in lines:
        if ln.startswith(b"$S,"):
            k += 1
            if k % 4 == 0:
                f = fields(ln)
                ln = encode_line("U", (f[1], f[2], 20000, -30000, 40000, f[6], f[7]))
        mixed.append(ln)
    plain, _, _ = fit_offset(capsys, write_capture(tmp_path / "a.cap", lines))
    offset, reading, err = fit_offset(capsys, write_capture(tmp_path / "b.cap", [b"".join(mixed)]))
    assert reading["calibrated_lines"] == N // 4 and "768 calibrated (U) lines left out" in err
    assert np.linalg.norm(offset - plain) < 0.5
    assert len(load_series(tmp_path / "b.cap")) == N - N // 4


def test_a_capture_of_calibrated_output_only_is_named(tmp_path, lines, capsys):
    cal = [encode_line("U", (*fields(ln)[1:3], 1, 2, 3, 0, 0)) for ln in lines if ln.startswith(b"$S,")]
    path = write_capture(tmp_path / "u.cap", [lines[0], *cal])
    assert main(["fit", str(path)]) == 6  # a file that cannot be used
    assert f"all {N} sample lines are calibrated (U) readings" in capsys.readouterr().err


def _hello_with(line: bytes, seq: int, asa) -> bytes:
    f = fields(line)
    return encode_line("H", (seq, *f[2:6], *asa, f[9]))


@pytest.mark.parametrize("asa", [(9999, 9999, 9999), (250, 250, 250)])
def test_a_mid_stream_hello_cannot_rescale_later_samples(tmp_path, lines, capsys, asa):
    """A hello with a valid CRC but another ASA (out of range, or in range) in the middle of
    the stream: the samples after it keep the chip's gain (it was × 39 before)."""
    hello = next(ln for ln in lines if ln.startswith(b"$H,"))
    i = len(lines) // 2
    seq = int(fields(lines[i - 1])[1]) + 1
    tampered = [*lines[:i], _hello_with(hello, seq, asa), *[_renumber(ln, +1) for ln in lines[i:]]]
    plain = load_series(write_capture(tmp_path / "a.cap", lines))
    s = load_series(write_capture(tmp_path / "b.cap", [b"".join(tampered)]))
    assert np.array_equal(s.field_ut, plain.field_ut)
    key = "bad_syntax" if asa[0] > 255 else "hellos_refused"
    assert s.reading[key] == 1
    live = read_to_end(open_device(f"replay://{tmp_path / 'b.cap'}?pace=0"))  # the live client agrees
    assert np.array_equal(np.array([x.field_ut for x in live]), plain.field_ut)


def _renumber(line: bytes, by: int) -> bytes:
    f = fields(line)
    f[1] = str((int(f[1]) + by) % 65536)
    return encode_line(f[0], f[1:])


def test_resent_lines_are_taken_once_and_lost_lines_counted_as_lost(tmp_path, lines, capsys):
    """137 copies of older lines re-sent among the stream, and 760 lines dropped in 19 gaps:
    the copies were counted twice into the fit and lost_lines read millions."""
    rng = np.random.default_rng(7)
    samples = [ln for ln in lines if ln.startswith(b"$S,")]
    dropped = set()
    for start in rng.choice(np.arange(100, N - 100, 150), 19, replace=False):
        dropped.update(range(int(start), int(start) + 40))
    out, resent = lines[: lines.index(samples[0])], 0  # the hellos and replies before the stream
    for k, ln in enumerate(samples):
        if k in dropped:
            continue
        out.append(ln)
        if k > 60 and k % 15 == 0 and resent < 137:
            out.append(samples[k - int(rng.integers(1, 60))])  # an older line again
            resent += 1
    s = load_series(write_capture(tmp_path / "d.cap", [b"".join(out)]))
    assert resent == 137
    assert s.reading["duplicate_lines"] == 137, s.reading
    assert s.reading["lost_lines"] == len(dropped) == 760 and s.reading["gaps"] == 19
    assert len(s) == N - 760 and len(np.unique(s.seq)) == len(s)
    _, reading, err = fit_offset(capsys, tmp_path / "d.cap")
    assert reading["duplicate_lines"] == 137 and "137 duplicate or late lines taken once" in err


def test_no_loss_is_counted_where_none_was(tmp_path, lines):
    """Two late copies in a clean stream: lost_lines read 131 070."""
    out = [*lines[:500], lines[400], *lines[500:1000], lines[990], *lines[1000:]]
    s = load_series(write_capture(tmp_path / "e.cap", [b"".join(out)]))
    assert s.reading.get("lost_lines", 0) == 0 and s.reading["duplicate_lines"] == 2 and len(s) == N


def _chunked(lines, per=16):
    return [b"".join(lines[i : i + per]) for i in range(0, len(lines), per)]


def test_a_flipped_chunk_marker_loses_nothing_and_is_reported(tmp_path, lines, capsys):
    """One flipped marker byte silently dropped 2112 of 3072 samples."""
    path = write_capture(tmp_path / "f.cap", _chunked(lines))
    blob = bytearray(path.read_bytes())
    marks = [m.start() for m in re.finditer(b"K", bytes(blob))]
    r = CaptureReader(path)
    starts = [a - CHUNK_OVERHEAD for a, _ in r._spans]
    at = starts[len(starts) // 3]
    assert at in marks
    blob[at] ^= 0x5A
    path.write_bytes(bytes(blob))
    s = load_series(path)
    assert len(s) == N and s.reading["damaged_chunks"] == 1 and s.reading.get("skipped_bytes", 0) == 0
    _, reading, err = fit_offset(capsys, path)
    assert "1 damaged capture chunks" in err and reading["damaged_chunks"] == 1


@pytest.mark.parametrize("byte", [2, 9, 10])  # in the receive time; in the size (low, high byte)
def test_a_damaged_chunk_header_costs_that_chunk_at_most(tmp_path, lines, byte):
    path = write_capture(tmp_path / "g.cap", _chunked(lines))
    r = CaptureReader(path)
    starts = [a - CHUNK_OVERHEAD for a, _ in r._spans]
    blob = bytearray(path.read_bytes())
    at = starts[len(starts) // 2]
    blob[at + byte] ^= 0xFF
    path.write_bytes(bytes(blob))
    s = load_series(path)
    # a flipped time byte that still reads as a plausible time is no loss and cannot be seen
    assert N - 16 <= len(s) <= N and (s.reading.get("damaged_chunks", 0) == 1 or len(s) == N)
    assert "truncated_bytes" not in s.reading


def test_the_daemon_counts_the_same_and_shows_every_defect(tmp_path, lines):
    """The same damaged stream through the daemon (a replay is read as the live link reads):
    duplicates never fitted, lost lines as lost, and every framing defect among the faults in
    its status, its state file and ``magcal status --json`` (24 MiB of garbage left faults {})."""
    from magcal.app import config
    from magcal.app.daemon import Daemon
    from magcal.recordings.state import StateFiles

    samples = [ln for ln in lines if ln.startswith(b"$S,")]
    out = lines[: lines.index(samples[0])]
    garbage = np.random.default_rng(3).integers(0, 256, 24 * 1024, dtype=np.uint8).tobytes().replace(b"$", b"#")
    for k, ln in enumerate(samples):
        if 1000 <= k < 1040:
            continue  # 40 lines lost
        out.append(ln)
        if k % 100 == 50:
            out.append(samples[k - 7])  # 31 older lines again
        if k == 2000:
            out.append(garbage + ln[:20] + b"\n")  # noise, then a torn line... and a cut line
            out.append(ln[:-3] + (b"00" if ln[-3:-1] != b"00" else b"11") + b"\n")  # a bad checksum
    cap = write_capture(tmp_path / "d.cap", _chunked(out, per=64))
    settings = config.load(overrides={"port": f"replay://{cap}?pace=0"}, environ={})
    d = Daemon(settings, state_dir=tmp_path / "state")
    d.run()
    f = d.faults
    assert f["duplicate_lines"] == 31 and f["lost_lines"] == 40 and f["gaps"] == 1
    assert f["noise_bytes"] >= 24 * 1024 and f["bad_checksums"] == 1 and f["malformed_lines"] + f["torn_lines"] >= 1
    status = d.status()
    assert status["samples_in"] == N - 40 and status["faults"]["noise_bytes"] == f["noise_bytes"]
    saved = StateFiles(tmp_path / "state").load()["status"]["faults"]
    assert saved["duplicate_lines"] == 31 and saved["bad_checksums"] == 1 and saved["noise_bytes"] >= 24 * 1024
    assert main(["status", "--state-dir", str(tmp_path / "state"), "--json"]) == 1  # stopped: state file
