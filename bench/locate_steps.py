"""Change points in time: hard-iron steps and soft-iron changes injected into simulated and real
raw recordings, judged on what ``magcal.diagnose.locate.steps`` says and where.

    python bench/locate_steps.py [--quick] [--seeds N]

Each case is a recording (hand-waved or tilted simulations, and the real raw recordings of
../shared/data/real via bench/real_recordings.py) with one step of the offset (a random
direction, 2, 4 or 10 × the recording's floor) or one gain change of an axis (the same size at
the field, relative) at a random time in the middle 30–70 % of the span, and the same
recording without it as a control. The calibration searched is a plain ellipsoid fitted on the
samples (what the diagnosis starts from). Printed per size: located (the right effect, time
within ±1 s or 5 % of the span), named (the effect or ``unexplained_structure``), a specific
false claim in the effect case (another named effect, or the right one in the wrong place),
and specific claims on the controls.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import real_recordings  # noqa: E402

from magcal.diagnose.locate import steps  # noqa: E402
from magcal.diagnose.locate.base import REST, Kind, Residual  # noqa: E402
from magcal.fit import fit_calibration  # noqa: E402
from magcal.sim.physics import Motion, Physics, Scenario  # noqa: E402

MAX_N = 6000


def recordings(quick: bool, seeds: int) -> dict:
    out = {}
    for seed in range(seeds):
        for motion in (Motion("sphere", period_s=20.0), Motion("tilt", max_tilt_deg=50.0)):
            run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=motion,
                           seed=100 + seed).simulate(4000, 50.0)
            out[f"sim_{motion.kind}_{seed}"] = (run.series.t_s, run.series.field_ut)
    out.update(real_recordings.raw_in_ut(quick, MAX_N))
    return out


def search(t, m):
    fit = fit_calibration(m, model="ellipsoid")
    if not fit:
        return None
    return steps.search(Residual(t, m, fit.calibration, 0.0, float(fit.rms_ut)))


def inject(kind, t, m, rng, size):
    fit = fit_calibration(m, model="ellipsoid")
    fl, b = float(fit.rms_ut), fit.calibration.offset_ut
    tau = float(t[0] + (t[-1] - t[0]) * rng.uniform(0.3, 0.7))
    after = t >= tau
    out = m.copy()
    if kind == steps.STEP:
        d = rng.standard_normal(3)
        out += np.outer(after, d * size * fl / np.linalg.norm(d))
    else:
        axis = int(rng.integers(3))
        gain = 1.0 + size * fl / fit.calibration.field_ut
        out[after, axis] = b[axis] + gain * (m[after, axis] - b[axis])
    return out, tau


def judge(found, kind, tau, span):
    tol = max(1.0, 0.05 * span)
    named = [f for f in found if f.effect in (kind, REST)]
    hit = any(f.effect == kind and abs(f.where["time_s"][0] - tau) <= tol for f in found)
    false = any(f.kind is Kind.PHYSICS and not (f.effect == kind and abs(f.where["time_s"][0] - tau) <= tol)
                for f in found)
    return hit, bool(named), false


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--placements", type=int, default=2)
    a = ap.parse_args()
    recs = recordings(a.quick, a.seeds)
    rng = np.random.default_rng(7)
    tally, controls, clock = {}, [], []
    for name, (t, m) in recs.items():
        t0 = time.perf_counter()
        found = search(t, m)
        clock.append(time.perf_counter() - t0)
        if found is None:
            continue
        claims = [f.summary for f in found if f.kind is Kind.PHYSICS]
        controls.append(bool(claims))
        rest = [f.summary for f in found if f.kind is Kind.REMAINDER]
        print(f"control {name}: span {t[-1] - t[0]:.0f} s, claims {claims}, remainder {rest}")
        for kind in (steps.STEP, steps.SOFT):
            for size in (2, 4, 10):
                for _ in range(a.placements):
                    m2, tau = inject(kind, t, m, rng, size)
                    got = search(t, m2) or ()
                    row = judge(got, kind, tau, t[-1] - t[0])
                    tally.setdefault((kind, size, name.startswith("sim")), []).append(row)
                    if not row[0]:
                        print(f"  miss {name} {kind} {size}x at {tau:.1f}: {[f.summary for f in got]}")
    print("\nkind              size  data  cases  located  named  false")
    for (kind, size, sim), rows in sorted(tally.items()):
        r = np.array(rows, float)
        print(f"{kind:17s} {size:4d}  {'sim' if sim else 'real':4s} {len(r):6d}  {r[:, 0].mean():7.2f} "
              f"{r[:, 1].mean():6.2f} {r[:, 2].mean():6.2f}")
    print(f"controls: {len(controls)}, with a specific claim: {sum(controls)}; search time median "
          f"{np.median(clock):.2f} s, max {np.max(clock):.2f} s")


if __name__ == "__main__":
    main()
