"""Start-up: what a user waits for before ``magcal`` answers.

Run: python bench/startup.py [runs]   (default 15)

Times whole processes, as a user meets them, each run from start to exit:

1. ``python -c pass`` and ``python -c "import numpy"`` — the floor any Python tool pays;
2. ``magcal --help``                                  — target ≤ 0.15 s;
3. ``magcal fit small.csv`` (324 rows, 6.5 s at 50 Hz) — target ≤ 0.4 s;
4. in-process: reading a 300 000-row table (``load_table``), the numpy path.

Each figure is the median over the runs (min and max beside it), as wall seconds and as CPU
seconds (user + system of the child, from the operating system's accounting). On a shared
machine wall time also holds the time spent waiting for a processor; the CPU figure is the
work itself, and the two agree on an idle machine. The load average is printed so a reader can
tell which it was.
"""

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

TARGETS = {"magcal --help": 0.15, "magcal fit small.csv": 0.40}


def timed(argv, runs: int) -> tuple[list[float], list[float]]:
    """(wall seconds, CPU seconds) of each run of ``argv`` (after one warm-up run)."""
    env = dict(os.environ, PYTHONPATH=ROOT)
    walls, cpus = [], []
    for i in range(runs + 1):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        p = subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if p.returncode != 0:
            raise SystemExit(f"{' '.join(argv)} failed: {p.stderr.decode()[-400:]}")
        if i:  # the first run warms the file cache
            walls.append(wall)
            cpus.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
    return walls, cpus


def row(label: str, walls, cpus) -> str:
    target = TARGETS.get(label)
    t = f"≤ {target:.2f}" if target else "—"
    return (f"| {label} | {statistics.median(walls):.3f} ({min(walls):.3f}–{max(walls):.3f}) "
            f"| {statistics.median(cpus):.3f} ({min(cpus):.3f}–{max(cpus):.3f}) | {t} |")


def table_read(rows: int = 300_000) -> tuple[float, float]:
    """(CPU s, wall s) of ``load_table`` on a ``rows``-row magcal CSV."""
    import numpy as np

    from magcal.recordings.table import load_table

    rng = np.random.default_rng(1)
    m = rng.normal(size=(rows, 3)) * 30
    with tempfile.NamedTemporaryFile("w", suffix=".csv", delete=False) as f:
        f.write("t,mx,my,mz,temp_c\n")
        f.writelines(f"{i * 0.02!r},{a!r},{b!r},{c!r},{25.0 + i * 1e-5!r}\n" for i, (a, b, c) in enumerate(m.tolist()))
    try:
        c0, w0 = time.process_time(), time.perf_counter()
        s = load_table(f.name)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    finally:
        os.unlink(f.name)
    assert len(s) == rows
    return cpu, wall


def main(runs: int = 15) -> None:
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        small = os.path.join(tmp, "small.csv")
        subprocess.run([py, "-m", "magcal", "simulate", "-o", small, "--seconds", "6.48", "--rate", "50"],
                       env=dict(os.environ, PYTHONPATH=ROOT), check=True, stdout=subprocess.DEVNULL)
        cases = [
            ("python -c pass", [py, "-c", "pass"]),
            ("python -c 'import numpy'", [py, "-c", "import numpy"]),
            ("magcal --help", [py, "-m", "magcal", "--help"]),
            ("magcal fit small.csv", [py, "-m", "magcal", "fit", small]),
        ]
        print(f"start-up, {runs} runs each; load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
        print("| command | wall s, median (min–max) | CPU s, median (min–max) | target |")
        print("|---|---|---|---|")
        for label, argv in cases:
            print(row(label, *timed(argv, runs)), flush=True)
    cpu, wall = table_read()
    print(f"load_table, 300 000 rows: {cpu:.2f} s CPU ({wall:.2f} s wall)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 15)
