"""A capture is read block by block with bounded memory, and gives exactly what reading it
whole gives — samples, times, and every count (damage, duplicates, lost lines, hellos refused,
calibrated lines) — wherever the block boundaries fall: inside a line, inside a hello, next to
a damaged chunk marker."""

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.recordings.capture import CHUNK_OVERHEAD, CaptureReader, CaptureWriter, make_header, series_from_frames
from magcal.wire.bulk import parse_stream
from magcal.wire.protocol import encode_line

CHUNK = 37  # payload bytes per chunk: lines straddle chunks


def hello(seq, asa):
    return encode_line("H", (seq, 1, "0.1.0", "68", "48", *asa, 100))


def sample(seq, kind="S"):
    x = 100 + 7 * (seq % 13)
    return encode_line(kind, (seq, 10 * seq, x, -2 * x, 50 + seq % 5, 0, -3345))


def stream() -> tuple[bytes, int]:
    """A recording with one of each thing the reading counts; and where the refused hello is."""
    out = [hello(0, (128, 128, 128))]
    for k in range(1, 200):
        if 100 <= k < 105:
            continue  # 5 lines lost
        if k == 150:
            at = sum(map(len, out))
            out.append(hello(150, (200, 128, 128)))  # a changed ASA without a restart: refused
            continue
        out.append(sample(k, "U" if k == 120 else "S"))
        if k == 60:
            out.append(sample(60))  # re-sent: a duplicate
        if k == 80:
            out.append(b"xx noise\n$S,81,81")  # noise, and a line torn by the next one
    out.append(hello(0, (100, 100, 100)))  # the device restarts with another chip's ASA
    out += [sample(k) for k in range(1, 40)]
    return b"".join(out), at


@pytest.fixture
def damaged(tmp_path):
    """The capture, its chunk marker flipped where the refused hello starts."""
    data, at = stream()
    path = tmp_path / "d.cap"
    with CaptureWriter(path, make_header("sim://", None)) as w:
        for i in range(0, len(data), CHUNK):
            w.append(data[i : i + CHUNK], t_rx_s=0.01 * i)
    starts = [a - CHUNK_OVERHEAD for a, _ in CaptureReader(path)._spans]
    mark = starts[at // CHUNK]
    blob = bytearray(path.read_bytes())
    blob[mark] ^= 0x5A
    path.write_bytes(bytes(blob))
    return path, data, at, mark


def test_the_recording_holds_what_the_test_says(damaged):
    path, data, _, _ = damaged
    r = CaptureReader(path)
    assert r.data() == data and r.reading() == {"damaged_chunks": 1, "skipped_bytes": 0, "truncated_bytes": 0}
    s = load_series(path)
    want = {"duplicate_lines": 1, "lost_lines": 5, "gaps": 1, "hellos_refused": 1, "torn_lines": 1,
            "restarts": 1, "calibrated_lines": 1, "damaged_chunks": 1}
    assert {k: s.reading.get(k) for k in want} == want
    assert len(s) == 199 - 5 - 1 - 1 + 39  # no duplicate, no U line, the hello is no sample


@pytest.mark.parametrize("block", [61, 64, 97, 128, 211, 256, 1000, 4096, 1 << 22])
def test_any_block_size_reads_what_a_whole_read_does(damaged, block):
    path, data, at, mark = damaged
    whole_reader = CaptureReader(path, block_bytes=1 << 30)
    whole = series_from_frames(parse_stream(whole_reader.data()))
    r = CaptureReader(path, block_bytes=block)
    assert r.reading() == whole_reader.reading() and r.problem == whole_reader.problem
    assert np.array_equal(r.t_rx_s, whole_reader.t_rx_s) and r._spans == whole_reader._spans
    blocks = list(r.blocks())
    assert b"".join(blocks) == data
    s = series_from_frames(r.frames())
    assert s.reading == whole.reading and s.reading["hellos_refused"] == 1
    for got, ref in ((s.t_s, whole.t_s), (s.field_ut, whole.field_ut), (s.valid, whole.valid), (s.seq, whole.seq),
                     (s.channels["temp_c"], whole.channels["temp_c"])):
        assert got.dtype == ref.dtype and np.array_equal(got, ref, equal_nan=True)


def test_a_block_boundary_inside_the_hello_past_the_damaged_marker(damaged):
    """The case the blocks are for: the refused hello is cut between two blocks, and the damaged
    marker lies past memory the structure pass has already let go."""
    path, data, at, mark = damaged
    n_hello = len(hello(150, (200, 128, 128)))

    def cuts_hello(block):
        ends = np.cumsum([len(b) for b in CaptureReader(path, block_bytes=block).blocks()])
        return any(at < e < at + n_hello for e in ends)

    block = next(b for b in range(40, 400) if cuts_hello(b))
    assert mark > 4096 > block  # read through the memory map, past a released page
    s = series_from_frames(CaptureReader(path, block_bytes=block).frames())
    assert s.reading["hellos_refused"] == 1
    # the refused hello rescales nothing after it; the restart's hello (ASA 100) does
    before, after = s.field_ut[s.seq == 149][0], s.field_ut[s.seq == 151][0]
    assert np.allclose(before / np.array([100 + 7 * (149 % 13), -2 * (100 + 7 * (149 % 13)), 50 + 149 % 5]),
                       after / np.array([100 + 7 * (151 % 13), -2 * (100 + 7 * (151 % 13)), 50 + 151 % 5]))
    gain = ((100 - 128) / 256 + 1) / ((128 - 128) / 256 + 1)
    assert s.field_ut[-1][0] / s.field_ut[s.seq == 39][0][0] == pytest.approx(gain)
