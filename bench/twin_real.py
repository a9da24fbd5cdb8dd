"""The sensor twin on every real recording with at least 1000 magnetometer samples.

For each recording: the calibration ``magcal fit --model auto`` finds (a still recording takes
its session's full-sphere calibration), the sensor model learned around it
(``magcal.diagnose.twin.learn``), and the twin comparison step by step from the baseline (hard
iron + white noise) to the learned model, each step judged against ``--draws`` twins (default
50) on fresh seeds. Printed: per recording, how many statistics lie inside their twins'
2.5–97.5 % band at each step, and what the final model still misses; then the acceptance
count over all (recording, statistic) pairs, final beside baseline.

Run: MAGCAL_REAL_DATA=… python bench/twin_real.py [--draws 50] [--seed N] [--only SUBSTRING] [--ends]
     (≈ 10–20 min of CPU on one core; --ends makes two comparisons instead of up to ten;
     the seed is printed so a run can be repeated)
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402

import twin_recordings as tr  # noqa: E402
from magcal.diagnose import twin  # noqa: E402
from magcal.fit import fit_calibration as fit  # noqa: E402


def calibration_of(series, fixed):
    if fixed is not None:
        return fixed, False
    r = fit(series.field_ut, model="auto")
    if not r:
        r = fit(series.field_ut, model="sphere")
    return r.calibration, True


def run_one(name, draws, seed, ends=False):
    series, fixed = tr.load(name)
    series = series.only_valid()
    cal, free = calibration_of(series, fixed)
    t0 = time.process_time()
    model = twin.learn(series, cal, source={"recording": name}, free=free)
    if ends:  # the same two comparisons compare_steps makes first and last, on the same seeds
        rep = twin.TwinReport(model=model, steps=(
            twin.compare(twin.baseline_model(model, series, free), series, draws, seed, "baseline", free),
            twin.compare(model, series, draws, seed, "final", free)))
    else:
        rep = twin.compare_steps(model, series, draws=draws, seed=seed, free=free)
    return {"name": name, "n": len(series), "report": rep, "cpu_s": time.process_time() - t0}


def show(row) -> None:
    rep = row["report"]
    steps = "  ".join(f"{c.step} {c.inside}/{len(c.bands)}" for c in rep.steps)
    print(f"{row['name']:<40} {row['n']:>6}  {steps}   ({row['cpu_s']:.0f} s CPU)")
    for m in rep.final.mismatches:
        print(f"      final misses {m.statistic}: {m.summary}")
    sys.stdout.flush()


def summary(rows) -> str:
    fin = sum(r["report"].final.inside for r in rows)
    base = sum(r["report"].baseline.inside for r in rows)
    total_f = sum(len(r["report"].final.bands) for r in rows)
    total_b = sum(len(r["report"].baseline.bands) for r in rows)
    by_stat: dict = {}
    for r in rows:
        for b in r["report"].final.bands:
            key = "xcorr:<channel>" if b.name.startswith("xcorr:") else b.name
            k = by_stat.setdefault(key, [0, 0])
            k[0] += b.inside
            k[1] += 1
    lines = [f"recordings: {len(rows)}",
             f"final model : {fin}/{total_f} (recording, statistic) pairs inside the twins' 2.5–97.5 % band ({100 * fin / max(total_f, 1):.1f} %)",
             f"baseline    : {base}/{total_b} ({100 * base / max(total_b, 1):.1f} %)   [hard iron + white noise]",
             "per statistic (final): " + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in by_stat.items())]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=twin.DRAWS)
    p.add_argument("--seed", type=int, default=None, help="first seed (default: fresh, printed)")
    p.add_argument("--only", default=None, help="only recordings whose name contains this")
    p.add_argument("--ends", action="store_true",
                   help="only the baseline and the final model (the acceptance count, same figures; the steps between skipped)")
    args = p.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little")
    print(f"twin draws per step: {args.draws}; first seed {seed}; {tr.RATE_NOTE}")
    rows = []
    for name in tr.RECORDINGS:
        if args.only and args.only not in name:
            continue
        try:
            row = run_one(name, args.draws, seed, args.ends)
        except Exception as exc:  # a recording the tool cannot handle is reported, not hidden
            print(f"{name:<40} FAILED: {type(exc).__name__}: {exc}")
            continue
        if row["n"] < tr.MIN_SAMPLES:
            print(f"{name:<40} {row['n']} valid samples: below {tr.MIN_SAMPLES}, not counted")
            continue
        show(row)
        rows.append(row)
    print(summary(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
