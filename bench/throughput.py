"""Replay throughput: parse + accumulate a one-hour 100 Hz capture, and the batch accumulator.

Run: python bench/throughput.py [minutes]   (default 60 → 360 000 sample lines)

Builds the capture from the physics simulator (``demo_scenario``) as the sim board would send
it — a hello, then one ``S`` line per measurement, recorded in 50 ms chunks — then times:

Rates are per second of this process's CPU time (wall time printed beside it).

1. bulk path: read the capture file, ``protocol_bulk.parse_stream``, build the Series exactly
   as the live client would (``capture.series_from_frames``), ``SphereAccumulator.add_batch``;
2. ``load_series`` (what ``magcal fit FILE`` does), for comparison;
3. the incremental path (``ProtocolDevice`` over ``replay://``) on a 5-minute slice;
4. the batch accumulator alone.
Target (issue 2): ≥ 400 k lines/s for (1).
"""

import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.app.load import load_series  # noqa: E402
from magcal.devices import open_device  # noqa: E402
from magcal.devices.base import read_to_end  # noqa: E402
from magcal.fit import SphereAccumulator  # noqa: E402
from magcal.recordings.capture import (
    CaptureReader,
    CaptureWriter,
    make_header,
    series_from_frames,
)  # noqa: E402
from magcal.sim.physics import demo_scenario  # noqa: E402
from magcal.wire.bulk import parse_stream  # noqa: E402
from magcal.wire.protocol import encode_line  # noqa: E402

RATE_HZ = 100
CHUNK_S = 0.05


def make_capture(path: str, n: int) -> int:
    sc = demo_scenario(7)
    ms = np.arange(1, n + 1) * (1000 // RATE_HZ)
    raw, st2, temp = sc.measure(ms / 1000.0, np.arange(n))
    lines = [encode_line("H", (0, 1, "0.1.0", "68", "48", *sc.physics.asa, RATE_HZ))]
    for i in range(n):
        lines.append(encode_line("S", ((i + 1) % 65536, int(ms[i]), *(int(v) for v in raw[i]), int(st2[i]), int(temp[i]))))
    per = int(RATE_HZ * CHUNK_S)
    w = CaptureWriter(path, make_header("sim://?seed=7", 115200))
    for j in range(0, len(lines), per):
        w.append(b"".join(lines[j : j + per]), t_rx_s=j / RATE_HZ)
    w.close()
    return os.path.getsize(path)


def best_of(k, fn):
    """Best of k runs by CPU time of this process (a loaded machine inflates wall time, not
    this); the wall time of that run is kept in WALL for the printout."""
    times = []
    out = None
    for _ in range(k):
        t0, w0 = time.process_time(), time.perf_counter()
        out = fn()
        times.append((time.process_time() - t0, time.perf_counter() - w0))
    cpu, wall = min(times)
    WALL[0] = wall
    return cpu, out


WALL = [0.0]


def main() -> None:
    minutes = float(sys.argv[1]) if len(sys.argv) > 1 else 60.0
    n = int(minutes * 60 * RATE_HZ)
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "hour.cap")
        t0 = time.perf_counter()
        size = make_capture(path, n)
        print(f"capture: {n:,} sample lines, {size / 1e6:.1f} MB, built in {time.perf_counter() - t0:.1f} s")

        def bulk():
            frames = parse_stream(CaptureReader(path).data())
            s = series_from_frames(frames)
            acc = SphereAccumulator()
            acc.add_batch(s.field_ut[s.valid])
            return acc

        dt, acc = best_of(3, bulk)
        fit = acc.solve()
        print(f"bulk parse + accumulate: {n / dt:12,.0f} lines/s  ({dt:.3f} s CPU, {WALL[0]:.3f} s wall; target ≥ 400,000)"
              f"  offset {np.round(fit.offset_ut, 2).tolist()} µT")
        dt, s = best_of(3, lambda: load_series(path))
        print(f"load_series (fit's input): {len(s) / dt:10,.0f} lines/s  ({dt:.3f} s CPU, {WALL[0]:.3f} s wall)")

        k = min(n, 5 * 60 * RATE_HZ)
        part = os.path.join(d, "part.cap")
        make_capture(part, k)
        dt, samples = best_of(1, lambda: read_to_end(open_device(f"replay://{part}")))
        print(f"incremental ProtocolDevice replay: {len(samples) / dt:8,.0f} lines/s  ({k:,} lines)")

        m = s.field_ut
        for chunk in (100, 10_000, len(m)):
            def batch():
                acc = SphereAccumulator()
                for i in range(0, len(m), chunk):
                    acc.add_batch(m[i : i + chunk])
                return acc

            dt, _ = best_of(3, batch)
            print(f"batch accumulator, chunks of {chunk:>7,}: {len(m) / dt:14,.0f} samples/s")


if __name__ == "__main__":
    main()
