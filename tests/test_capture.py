"""Capture files: what a recording keeps, how it survives a crash or a full disk, size bounds,
and telling recordings apart by content."""

import errno
import json
import os

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.core.errors import InputError
from magcal.core.series import Series
from magcal.devices.base import read_to_end
from magcal.devices.protocol_client import ProtocolDevice
from magcal.devices.replay import BytesTransport
from magcal.recordings.capture import (
    CaptureReader,
    CaptureWriteError,
    CaptureWriter,
    make_header,
    roll_keep_one,
)
from magcal.wire.dialect import Dialect
from magcal.wire.protocol import encode_line


def stream_bytes(n=400, start=1):
    out = [encode_line("H", (0, 1, "0.1.0", "68", "48", 170, 180, 190, 100))]
    for i in range(start, start + n):
        out.append(encode_line("S", (i % 65536, 10 * i, 100 + i % 50, -200 + i % 70, 300 - i % 30, 0, -2000 + i)))
    return b"".join(out)


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        self.t += 0.01
        return self.t


def chunks_of(data, size):
    return [data[i : i + size] for i in range(0, len(data), size)]


def test_header_and_chunks_round_trip(tmp_path):
    path = tmp_path / "a.cap"
    header = make_header("/dev/ttyACM0", 115200, Dialect.NATIVE)
    with CaptureWriter(path, header, clock=Clock()) as w:
        for i, c in enumerate([b"abc", b"", b"\x00\xff\n", b"$S,1"]):
            w.append(c, t_rx_s=0.5 * i)
    r = CaptureReader(path)
    assert r.header["port"] == "/dev/ttyACM0" and r.header["baud"] == 115200
    assert r.header["format"] == "magcal-capture" and r.header["version"] == 1
    assert r.header["tool"].startswith("magcal ") and r.header["start_utc"].endswith("+00:00")
    assert list(r) == [(0.0, b"abc"), (1.0, b"\x00\xff\n"), (1.5, b"$S,1")]
    assert r.truncated_bytes == 0 and r.problem == ""
    # the header is one JSON line: readable with any tool
    first = path.read_bytes().split(b"\n", 1)[0]
    assert json.loads(first)["dialect"] == "native"


def test_a_capture_cut_anywhere_in_its_last_chunk_keeps_every_whole_chunk(tmp_path):
    path = tmp_path / "a.cap"
    data = stream_bytes(60)
    parts = chunks_of(data, 97)
    with CaptureWriter(path, make_header("sim://"), clock=Clock()) as w:
        for p in parts:
            w.append(p)
    blob = path.read_bytes()
    last_len = 13 + len(parts[-1])
    for cut in range(1, last_len):
        cut_path = tmp_path / "cut.cap"
        cut_path.write_bytes(blob[: len(blob) - cut])
        r = CaptureReader(cut_path)
        assert [c for _, c in r] == parts[:-1]
        assert r.truncated_bytes == last_len - cut
        assert "truncated" in r.problem
        s = load_series(cut_path)  # never fatal
        assert len(s) > 0


def test_tap_records_exactly_what_the_client_read(tmp_path):
    data = stream_bytes(300)
    w = CaptureWriter(tmp_path / "t.cap", make_header("x"), clock=Clock())
    dev = ProtocolDevice.over("x", BytesTransport([(0.0, c) for c in chunks_of(data, 77)]), passive=True, tap=w)
    samples = read_to_end(dev)
    w.close()
    assert len(samples) == 300
    assert CaptureReader(w.path).data() == data


class FailingFile:
    """A file that accepts ``room`` bytes, then fails like a full disk."""

    def __init__(self, fh, room):
        self.fh, self.room = fh, room

    def write(self, b):
        if len(b) > self.room:
            self.fh.write(b[: self.room])  # a partial write, as a real disk might leave
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(b)
        return self.fh.write(b)

    def __getattr__(self, name):
        return getattr(self.fh, name)


def test_disk_full_raises_once_and_loses_nothing_the_device_sent(tmp_path):
    data = stream_bytes(500)
    reference = Series.from_samples(
        read_to_end(ProtocolDevice.over("r", BytesTransport([(0.0, data)]), passive=True))
    )
    w = CaptureWriter(tmp_path / "full.cap", make_header("x"), clock=Clock())
    w._fh = FailingFile(w._fh, 2000)
    dev = ProtocolDevice.over("x", BytesTransport([(0.0, c) for c in chunks_of(data, 64)]), passive=True, tap=w)
    dev.open()
    got, errors = [], []
    while True:
        try:
            got.extend(i for i in dev.read(0.05) if hasattr(i, "field_ut"))
        except CaptureWriteError as exc:  # the caller keeps streaming
            errors.append(str(exc))
            continue
        except EOFError:
            break
    assert len(errors) == 1 and "disk full" in errors[0]
    s = Series.from_samples(got)
    assert np.array_equal(s.field_ut, reference.field_ut) and np.array_equal(s.t_s, reference.t_s)
    assert not w.recording and w.dropped_bytes > 0
    # what did reach the file is a valid capture: a prefix of the stream
    r = CaptureReader(w.path)
    assert r.truncated_bytes == 0
    assert data.startswith(r.data()) and 0 < len(r.data()) < len(data)


def test_size_bound_stops_recording_without_breaking_the_file(tmp_path):
    data = stream_bytes(500)
    w = CaptureWriter(tmp_path / "b.cap", make_header("x"), max_bytes=4000, clock=Clock())
    for c in chunks_of(data, 100):
        w.append(c)
    w.close()
    assert w.full and os.path.getsize(w.path) <= 4000
    r = CaptureReader(w.path)
    assert data.startswith(r.data()) and r.truncated_bytes == 0
    assert w.bytes_recorded + w.dropped_bytes == len(data)


def test_rolling_capture_keeps_the_previous_file(tmp_path):
    data = stream_bytes(500)
    path = tmp_path / "roll.cap"
    w = CaptureWriter(path, make_header("x"), max_bytes=3000, on_full=roll_keep_one, clock=Clock())
    for c in chunks_of(data, 100):
        w.append(c)
    w.close()
    assert w.rolls >= 5 and not w.full
    old, new = CaptureReader(str(path) + ".1"), CaptureReader(path)
    assert os.path.getsize(path) <= 3000 and os.path.getsize(str(path) + ".1") <= 3000
    assert data.endswith(old.data() + new.data())


def test_load_series_tells_recordings_apart_by_content(tmp_path):
    data = stream_bytes(120)
    cap = tmp_path / "rec.bin"
    with CaptureWriter(cap, make_header("x"), clock=Clock()) as w:
        w.append(data)
    raw = tmp_path / "dump.txt"
    raw.write_bytes(data)
    csv = tmp_path / "m.dat"
    csv.write_text("t,mx,my,mz\n0,1,2,3\n1,4,5,6\n")
    mc = tmp_path / "motioncal.log"
    mc.write_text("".join(f"Raw:0,0,8192,0,0,0,{100 + i},{-50 - i},{20 + i}\n" for i in range(10)))
    s_cap, s_raw = load_series(cap), load_series(raw)
    assert len(s_cap) == 120 and np.array_equal(s_cap.field_ut, s_raw.field_ut)
    assert load_series(csv).field_ut.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert np.allclose(load_series(mc).field_ut[0], [10.0, -5.0, 2.0])
    other = tmp_path / "junk.bin"
    other.write_bytes(b"\x00\x01hello there\n")
    with pytest.raises(InputError, match="junk.bin"):
        load_series(other)
    empty = tmp_path / "empty.cap"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        load_series(empty)


def test_a_capture_of_another_version_is_refused_by_name(tmp_path):
    p = tmp_path / "v9.cap"
    p.write_bytes(json.dumps({"format": "magcal-capture", "version": 9}).encode() + b"\n")
    with pytest.raises(InputError, match="version 9"):
        CaptureReader(p)


def test_numbers_beyond_int64_take_the_live_clients_path(tmp_path):
    data = stream_bytes(50) + encode_line("S", (51, 2**70, 1, 2, 3, 0, 0)) + encode_line("S", (52, 5, 1, 2, 3, 0, 0))
    p = tmp_path / "odd.cap"
    with CaptureWriter(p, make_header("x"), clock=Clock()) as w:
        w.append(data)
    s = load_series(p)
    ref = Series.from_samples(read_to_end(ProtocolDevice.over("r", BytesTransport([(0.0, data)]), passive=True)))
    assert len(s) == 52 and np.array_equal(s.t_s, ref.t_s) and np.array_equal(s.field_ut, ref.field_ut)


def test_record_refused_before_reading_leaves_no_empty_capture(tmp_path, capsys):
    from magcal.cli import main

    out = tmp_path / "never.cap"
    rc = main(["record", "--port", "sim://?pace=0", "--dialect", "motioncal", "-o", str(out), "--count", "5"])
    assert rc == 2 and "needs a serial port" in capsys.readouterr().err
    assert not out.exists()


def test_a_raw_serial_dump_with_reset_noise_is_read_like_its_capture(tmp_path):
    # `cat /dev/ttyACM0 > dump.txt` across a board reset: NUL and 0xFF bytes before the lines
    from magcal.app.load import load_series
    from magcal.cli import main
    from magcal.recordings.capture import CaptureReader

    cap = tmp_path / "run.cap"
    assert main(["record", "--port", "sim://?pace=0&seed=6", "-o", str(cap), "--count", "200"]) == 0
    dump = tmp_path / "dump.txt"
    dump.write_bytes(b"\x00\x00\xff\x00" + CaptureReader(cap).data())
    a, b = load_series(cap), load_series(dump)
    assert len(b) == len(a) >= 200 and (b.field_ut == a.field_ut).all()


def test_a_capture_naming_an_unknown_dialect_is_refused_by_name(tmp_path, capsys):
    """A header whose dialect magcal does not know is an input error naming the file, the value
    and the dialects it reads — for the loaders and for ``replay://`` alike."""
    from magcal.cli import main

    path = tmp_path / "odd.cap"
    header = {**make_header("sim://", None), "dialect": "zzz"}
    path.write_bytes(json.dumps(header).encode() + b"\n")
    with pytest.raises(InputError, match=r"odd\.cap line 1: unknown dialect 'zzz' \(native, motioncal, auto\)"):
        load_series(str(path))
    assert main(["stream", "--port", f"replay://{path}", "--count", "1"]) != 0
    assert "unknown dialect 'zzz'" in capsys.readouterr().err
