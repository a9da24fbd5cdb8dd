"""The sensor twin learned from a real ICM-20948 or MPU-9250 recording, driven through the
simulated chip of the same kind (its register quantum, range and overflow:
``magcal.core.chips`` via ``Physics.to_counts``), measured with the twin bench's own
comparison: how many of the recording-vs-twins statistics a chip-driven recording keeps inside
the twins' 2.5–97.5 % band, beside the real recording's own count and beside a plain twin draw
(the same model, no chip: what a perfect chip model would score, the bench's own reference).
The chip-driven recording is loaded as the real one was (the AK8963 log's repeated rows dropped:
``twin_recordings.estibone``). Figures pooled over ``--seeds`` comparisons whose seeds lie
``spacing`` apart (each with twins of its own); pass: ≥ 90 % of the
statistics inside, twin_real.py's criterion.

Run: MAGCAL_REAL_DATA=… python bench/twin_chips.py [--draws 50] [--seed N] [--seeds 10]
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402

import twin_recordings as tr  # noqa: E402
from twin_real import calibration_of  # noqa: E402
from magcal.core.chips import ICM20948, MPU9250_16  # noqa: E402
from magcal.diagnose import twin  # noqa: E402
from magcal.diagnose.twin.draw import twin_directions, twin_readings  # noqa: E402
from magcal.diagnose.twin.residual import with_time  # noqa: E402
from magcal.sim.physics import Physics, Scenario  # noqa: E402

# (recording, chip, its loader keeps only rows where the reading changed)
PAIRS = (("icm20948 umich preflight", ICM20948, False), ("ak8963 estibone test1", MPU9250_16, True))
PASS_SHARE = 0.90  # twin_real.py's acceptance


def chip_driven(model, series, chip, seed: int, distinct: bool = False):
    """A recording of ``series``' times and directions: the twin's field read through ``chip``'s registers."""
    m, valid = twin_readings(model, twin_directions(model, series), series.t_s, with_time(series), seed)
    sc = Scenario(physics=Physics(chip=chip, asa=asa_of(model, chip)))
    raw, st2 = sc.to_counts(np.asarray(m, dtype=np.float64))
    ok = np.asarray(valid, bool) & (st2 == 0)
    if distinct:  # as the real log was loaded: a row equal to the one before is the same conversion
        ok &= np.concatenate([[True], np.any(np.diff(raw, axis=0) != 0, axis=1)])
    return replace(series, field_ut=raw * sc.physics.lsb_ut, valid=ok).only_valid()


def plain_twin(model, series, seed: int):
    """The reference: one twin draw of the same model, no chip in between."""
    m, valid = twin_readings(model, twin_directions(model, series), series.t_s, with_time(series), seed)
    return replace(series, field_ut=np.asarray(m, dtype=np.float64), valid=np.asarray(valid, bool)).only_valid()


def asa_of(model, chip) -> tuple[int, int, int]:
    """The ASA bytes that give the recording's own step (quantum = µT per count · (ASA+128)/256)."""
    q = np.asarray(getattr(model, "quantum_ut", None) or (chip.ut_per_count,) * 3, dtype=np.float64)
    if not chip.has_asa:
        return (128, 128, 128)
    return tuple(int(np.clip(round(v / chip.ut_per_count * 256 - 128), 0, 255)) for v in q)


def inside(rep) -> tuple[int, int]:
    return sum(b.low <= b.real <= b.high for b in rep.bands), len(rep.bands)


def outside(rep) -> list[str]:
    return [b.name for b in rep.bands if not b.low <= b.real <= b.high]


def spacing(draws: int) -> int:
    """Seeds of successive comparisons this far apart: each draws its own twins (consecutive
    seeds shared all but one of their draws, one band counted ten times)."""
    return max(1000, 2 * draws + 2)


def one_chip(name, chip, distinct, draws, seeds) -> dict:
    """Pooled (inside, total) and the statistics outside, per kind of recording."""
    series, fixed = tr.load(name)
    series = series.only_valid()
    cal, free = calibration_of(series, fixed)
    model = twin.learn(series, cal, source={"recording": name}, free=free)
    # a twin recording's seed sits half a spacing past its comparison's draw seeds (s … s + draws − 1)
    offset = spacing(draws) // 2
    kinds = {"real recording": lambda s: series, "chip-driven": lambda s: chip_driven(model, series, chip, s + offset, distinct),
             "plain twin": lambda s: plain_twin(model, series, s + offset)}
    out = {k: [0, 0, Counter()] for k in kinds}
    for seed in seeds:
        for kind, make in kinds.items():
            rep = twin.compare(model, make(seed), draws, seed, "final", free)
            got = inside(rep)
            out[kind][0] += got[0]
            out[kind][1] += got[1]
            out[kind][2].update(outside(rep))
    print(f"{name:<26} n={len(series):5d}  {chip.label}  ASA {asa_of(model, chip)}  quantum_ut "
          f"{tuple(round(q, 4) for q in model.quantum_ut)}")
    for kind, (k, n, missed) in out.items():
        print(f"  {kind:<15} {k:4d}/{n:<4d} inside ({100.0 * k / max(n, 1):5.1f} %, "
              f"{'pass' if k >= PASS_SHARE * n else 'below'} {PASS_SHARE:.0%})   outside: "
              + (", ".join(f"{s} ×{c}" for s, c in missed.most_common()) or "none"))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=50)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--seeds", type=int, default=10)
    args = p.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little") % 1_000_000
    seeds = range(seed, seed + args.seeds * spacing(args.draws), spacing(args.draws))
    print(f"draws {args.draws}; seeds {seeds[0]}, {seeds[1] if len(seeds) > 1 else ''} … {seeds[-1]}")
    for name, chip, distinct in PAIRS:
        one_chip(name, chip, distinct, args.draws, seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
