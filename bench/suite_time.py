"""The test suite's time: what a contributor waits for before ``make test`` (or ``make check``) answers.

Run: python bench/suite_time.py [--runs N] [--tier test|check|serial]   (default: 3 runs of test)

Times the same pytest command the Makefile runs, as whole processes, from start to exit:

- ``test``:   the whole suite on every core (``make test``: ``-n auto --dist loadgroup``)
              — target ≤ 300 s on a quiet 2-core machine;
- ``check``:  the fast tier, the tests marked slow left out (``make check``) — target ≤ 90 s;
- ``serial``: the whole suite in one process (no pytest-xdist), for comparison.

For each run it prints the wall seconds, the CPU seconds (user + system of pytest and all it
started, from the operating system's accounting) and pytest's own summary line; then the median,
min and max. On a shared machine wall time also holds the time spent waiting for a processor:
the load average before each run is printed so a reader can tell which it was. Timings live
here, never in a test.
"""

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import time

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

PARALLEL = ["-n", "auto", "--dist", "loadgroup"]
TIERS = {
    "test": (PARALLEL, 300.0),
    "check": (PARALLEL + ["-m", "not slow"], 90.0),
    "serial": ([], None),
}


def command(tier: str) -> list[str]:
    """The pytest command of ``tier`` (the Makefile's, with the same interpreter)."""
    return [sys.executable, "-m", "pytest", "-q", *TIERS[tier][0]]


def summary(output: str) -> str:
    """pytest's last line (``N passed, M skipped in S s``), or a note when there is none."""
    lines = [ln for ln in output.strip().splitlines() if re.search(r"\b(passed|failed|error)", ln)]
    return lines[-1].strip("= ") if lines else "(no pytest summary)"


def timed(argv: list[str]) -> tuple[float, float, str, int]:
    """(wall s, CPU s, pytest's summary, exit status) of one run of ``argv`` in the project root."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, summary(p.stdout + p.stderr), p.returncode


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="how many times to run the suite (default 3)")
    ap.add_argument("--tier", choices=sorted(TIERS), default="test", help="which command to time (default test)")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error("--runs must be at least 1")
    argv_ = command(args.tier)
    target = TIERS[args.tier][1]
    print(f"suite time, {args.tier}: {' '.join(argv_[1:])}  ({os.cpu_count()} cores)")
    walls, status = [], 0
    for i in range(args.runs):
        load = os.getloadavg()[0]
        wall, cpu, said, code = timed(argv_)
        walls.append(wall)
        status = status or code
        print(f"  run {i + 1}: {wall:7.1f} s wall  {cpu:7.1f} s CPU  load before {load:4.1f}  {said}", flush=True)
    print(f"  median {statistics.median(walls):.1f} s wall (min {min(walls):.1f}, max {max(walls):.1f})"
          + (f"; target ≤ {target:.0f} s on a quiet 2-core machine" if target else ""))
    return 1 if status else 0


if __name__ == "__main__":
    sys.exit(main())
