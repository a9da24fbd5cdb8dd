"""The sensor twin learned from a real ICM-20948 or MPU-9250 recording, driven through the
simulated chip of the same kind (its register quantum, range and overflow:
``magcal.core.chips`` via ``Physics.to_counts``), measured with the twin bench's own
comparison: how many of the recording-vs-twins statistics a chip-driven recording keeps inside
the twins' 2.5–97.5 % band, beside the real recording's own count.

Run: MAGCAL_REAL_DATA=… python bench/twin_chips.py [--draws 20] [--seed N]
"""

from __future__ import annotations

import argparse
import os
import sys
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

PAIRS = (("icm20948 umich preflight", ICM20948), ("ak8963 estibone test1", MPU9250_16))


def chip_driven(model, series, chip, seed: int):
    """A recording of ``series``' times and directions: the twin's field read through ``chip``'s registers."""
    m, valid = twin_readings(model, twin_directions(model, series), series.t_s, with_time(series), seed)
    sc = Scenario(physics=Physics(chip=chip, asa=asa_of(model, chip)))
    raw, st2 = sc.to_counts(np.asarray(m, dtype=np.float64))
    ok = np.asarray(valid, bool) & (st2 == 0)
    return replace(series, field_ut=raw * sc.physics.lsb_ut, valid=ok).only_valid()


def asa_of(model, chip) -> tuple[int, int, int]:
    """The ASA bytes that give the recording's own step (quantum = µT per count · (ASA+128)/256)."""
    q = np.asarray(getattr(model, "quantum_ut", None) or (chip.ut_per_count,) * 3, dtype=np.float64)
    if not chip.has_asa:
        return (128, 128, 128)
    return tuple(int(np.clip(round(v / chip.ut_per_count * 256 - 128), 0, 255)) for v in q)


def inside(rep) -> tuple[int, int]:
    return sum(b.low <= b.real <= b.high for b in rep.bands), len(rep.bands)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=20)
    p.add_argument("--seed", type=int, default=None)
    args = p.parse_args(argv)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little")
    print(f"draws {args.draws}; first seed {seed}")
    for name, chip in PAIRS:
        series, fixed = tr.load(name)
        series = series.only_valid()
        cal, free = calibration_of(series, fixed)
        model = twin.learn(series, cal, source={"recording": name}, free=free)
        real = inside(twin.compare(model, series, args.draws, seed, "final", free))
        driven = chip_driven(model, series, chip, seed + 10_000)
        chip_rep = twin.compare(model, driven, args.draws, seed, "final", free)
        got = inside(chip_rep)
        missed = ", ".join(b.name for b in chip_rep.bands if not b.low <= b.real <= b.high) or "none"
        print(f"{name:<28} n={len(series):6d}  {chip.label:<32} ASA {asa_of(model, chip)}  real recording {real[0]}/{real[1]} inside; "
              f"chip-driven {got[0]}/{got[1]} inside (outside: {missed})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
