"""Large files: memory and CPU time of reading and fitting them, and whether they grow linearly.

    python bench/scale.py [--rows 300000,1000000,3000000] [--dir DIR] [--keep]

For each size it writes a table (``t,mx,my,mz,temp_c``, a simulated sphere with noise) and a
magcal capture of the same number of protocol-v1 sample lines, then runs ``magcal fit FILE
--json`` on each in a fresh process and prints that process's CPU time, peak resident memory
(``VmHWM`` in ``/proc/self/status``; elsewhere ``ru_maxrss``, which on Linux also carries over
the size of the process that started it) and CPU time per million rows. Linear means the
per-row figure stays flat as the rows grow (the ratio to the smallest size is printed). It also times files a
table reader must not choke on: one line of 15 MB (refused by name), and a header of 80 000
columns (refused by name), each in a fresh process.

Targets: 3 M rows within 500 MB and linear; a 15 MB one-line file refused or read in seconds.
Figures in bench/README.md were measured with this script (CPU seconds, not wall clock).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

CHILD = r"""
import json, resource, sys, time
from magcal.cli import main
t0 = time.process_time()
code = main(sys.argv[1:])
peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:  # Linux carries ru_maxrss over exec from the forking parent; VmHWM is this process's own
    with open("/proc/self/status") as fh:
        peak_kb = next(int(ln.split()[1]) for ln in fh if ln.startswith("VmHWM:"))
except (OSError, StopIteration):
    pass
print(json.dumps({"code": code, "cpu_s": time.process_time() - t0, "maxrss_mb": peak_kb / 1024}),
      file=sys.stderr)
"""


def run_fit(path: str, *extra: str) -> dict:
    """``magcal fit PATH`` in a fresh process: its exit code, CPU time and peak memory."""
    p = subprocess.run([sys.executable, "-c", CHILD, "fit", path, "--json", *extra], capture_output=True,
                       text=True, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"})
    stats = json.loads(p.stderr.strip().splitlines()[-1])
    stats["message"] = next((ln for ln in p.stderr.splitlines() if ln.startswith("magcal fit:")), "")
    return stats


def sphere(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    m = np.array([23.0, -41.0, 12.0]) + 48.0 * u + rng.normal(scale=0.3, size=(n, 3))
    return np.arange(n) * 0.01, m


def write_table(path: str, n: int) -> None:
    t, m = sphere(n)
    temp = 25.0 + 0.5 * np.sin(t / 600.0)
    with open(path, "w") as fh:
        fh.write("t,mx,my,mz,temp_c\n")
        for a in range(0, n, 200_000):
            b = min(n, a + 200_000)
            block = np.column_stack([t[a:b], m[a:b], temp[a:b]])
            np.savetxt(fh, block, fmt=["%.2f", "%.4f", "%.4f", "%.4f", "%.3f"], delimiter=",")


def write_capture(path: str, n: int) -> None:
    """n sample lines: one full cycle of sequence numbers (65 536 lines) encoded once, then
    repeated (the numbering wraps as a device's does)."""
    from magcal.core.sample import UT_PER_COUNT
    from magcal.recordings.capture import CaptureWriter, make_header
    from magcal.wire.protocol import encode_line

    _, m = sphere(65536, seed=2)
    counts = np.round(m / UT_PER_COUNT).astype(int)
    cycle_lines = [encode_line("S", (k, 10 * k, *counts[k], 0, -3345)) for k in range(65536)]
    cycle = b"".join(cycle_lines)
    hello = encode_line("H", (0, 1, "0.1.0", "68", "48", 128, 128, 128, 100))
    lines_per_chunk = 64
    step = len(cycle) // 65536 * lines_per_chunk
    with CaptureWriter(path, make_header("bench://", None)) as w:
        w.append(hello, t_rx_s=0.0)
        left, t = n, 0.0
        while left > 0:
            k = min(left, 65536)
            part = cycle if k == 65536 else b"".join(cycle_lines[:k])
            for a in range(0, len(part), step):
                t += 0.64
                w.append(part[a : a + step], t_rx_s=t)
            left -= k


def one_line_files(d: str) -> list[tuple[str, str]]:
    out = []
    p = os.path.join(d, "one_line_15mb.csv")
    with open(p, "w") as fh:
        fh.write(",".join("1.5" for _ in range(3_700_000)) + "\n")
    out.append(("one line of 15 MB", p))
    p = os.path.join(d, "header_80k_columns.csv")
    with open(p, "w") as fh:
        fh.write(",".join(f"c{i}" for i in range(80_000)) + "\n" + ",".join("1.5" for _ in range(80_000)) + "\n")
    out.append(("a header of 80 000 columns", p))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default="300000,1000000,3000000")
    ap.add_argument("--dir", default=None, help="where to write the files (default: a temporary directory)")
    ap.add_argument("--keep", action="store_true", help="keep the files")
    args = ap.parse_args()
    sizes = [int(x) for x in args.rows.split(",")]
    d = args.dir or tempfile.mkdtemp(prefix="magcal-scale-")
    os.makedirs(d, exist_ok=True)
    print(f"{'file':<10} {'rows':>9} {'MB':>7} {'exit':>4} {'CPU s':>7} {'CPU s/M rows':>12} {'ratio':>6} {'peak MB':>8}")
    for kind, writer in (("table", write_table), ("capture", write_capture)):
        base = None
        for n in sizes:
            path = os.path.join(d, f"{kind}_{n}.{'csv' if kind == 'table' else 'cap'}")
            if not os.path.exists(path):
                writer(path, n)
            r = run_fit(path)
            per = r["cpu_s"] / (n / 1e6)
            base = base or per
            print(f"{kind:<10} {n:>9} {os.path.getsize(path) / 1e6:>7.1f} {r['code']:>4} {r['cpu_s']:>7.1f} "
                  f"{per:>12.2f} {per / base:>6.2f} {r['maxrss_mb']:>8.0f}")
            if not args.keep:
                os.remove(path)
    for what, path in one_line_files(d):
        t0 = time.perf_counter()
        r = run_fit(path, "--columns", "1,2,3")
        print(f"{what}: exit {r['code']}, {r['cpu_s']:.2f} CPU s in the fit command, "
              f"{time.perf_counter() - t0:.1f} s wall with start-up, peak {r['maxrss_mb']:.0f} MB — {r['message']}")
        os.remove(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
