"""Offset accuracy of the sphere fits against the Cramér–Rao bound on partial coverage.

Trials: the simulator's "tilt" motion (level within ±30°, yaw free), σ = 0.4 µT white noise,
0.3 µT quantum (× ASA gain), 1500 samples at 50 Hz, a random hard iron per trial. For each trial
the CRLB of the offset is σ_eff²(JᵀJ)⁻¹ at the true parameters and the trial's own true
directions, σ_eff² = σ² + q²/12 (q the per-axis quantum). Printed for ``fit_calibration(model="sphere")`` and for the
normal equations (the accumulator) on the same trials: the pooled ratio RMS offset error /
RMS √trace(CRLB), the per-trial ratio √mean(|error|² / trace CRLB) (steadier: trials differ in
coverage, and a few thin ones dominate pooled sums), and the mean Mahalanobis distance of the
error under the CRLB divided by 3 (1.0 = efficient).

Run: python bench/fit_crlb.py [trials]
"""

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.core.sample import UT_PER_COUNT, asa_gain  # noqa: E402
from magcal.fit import SphereAccumulator, fit_calibration  # noqa: E402
from magcal.fit.uncertainty import crlb_offset  # noqa: E402
from magcal.sim.physics import Motion, Physics, Scenario  # noqa: E402

NOISE_UT = 0.4
N = 1500


def trial(seed: int):
    rng = np.random.default_rng([seed, 77])
    b = rng.uniform(-60, 60, 3)
    ph = Physics(hard_iron_ut=tuple(b), noise_ut=NOISE_UT)
    run = Scenario(physics=ph, motion=Motion("tilt", max_tilt_deg=30.0), seed=seed).simulate(N)
    q = UT_PER_COUNT * np.array([asa_gain(a) for a in ph.asa])
    sigma_eff = float(np.sqrt(NOISE_UT**2 + np.mean(q**2) / 12.0))
    m_true = run.earth_ut + b
    C = crlb_offset(m_true, b, ph.field_ut, sigma_eff)
    gated = fit_calibration(run.series, model="sphere")
    ml = fit_calibration(run.series, model="sphere", max_condition=np.inf)  # the same fit, coverage gate off
    acc = SphereAccumulator()
    acc.add_batch(run.series.field_ut)
    alg = acc.solve(max_condition=np.inf)
    return dict(
        accepted=bool(gated),
        e_ml=np.sum((ml.calibration.offset_ut - b) ** 2),
        e_alg=np.sum((alg.offset_ut - b) ** 2),
        maha_ml=float((ml.calibration.offset_ut - b) @ np.linalg.solve(C, ml.calibration.offset_ut - b)),
        tr=np.trace(C),
        n_out=len(ml.outliers),
        d_ml=ml.calibration.offset_ut - b,
        d_alg=alg.offset_ut - b,
    )


def main() -> None:
    trials = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    t0 = time.perf_counter()
    rows = [trial(s) for s in range(trials)]
    dt = time.perf_counter() - t0
    col = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    print(f"{trials} trials: tilt ±30°, yaw free, σ = {NOISE_UT} µT + 0.3 µT quantum, {N} samples ({dt:.1f} s)")
    acc = col["accepted"]
    print(f"coverage gate (information condition ≤ 1e4) refused {int((~acc).sum())} of {trials} trials")
    for label, sel in (("accepted trials", acc), ("all trials, gate off", np.ones(trials, bool))):
        crlb = np.sqrt(np.mean(col["tr"][sel]))
        r_ml = np.sqrt(np.mean(col["e_ml"][sel]))
        r_alg = np.sqrt(np.mean(col["e_alg"][sel]))
        n_ml = np.sqrt(np.mean(col["e_ml"][sel] / col["tr"][sel]))
        n_alg = np.sqrt(np.mean(col["e_alg"][sel] / col["tr"][sel]))
        print(f"-- {label} ({int(sel.sum())}):  √trace(CRLB) RMS {crlb:.4f} µT")
        print(f"   fit --model sphere : RMS offset error {r_ml:.4f} µT  pooled ratio {r_ml / crlb:.3f}"
              f"  per-trial ratio {n_ml:.3f}  mean Mahalanobis/3 {np.mean(col['maha_ml'][sel]) / 3:.3f}"
              f"  mean error {np.round(col['d_ml'][sel].mean(axis=0), 3)} µT")
        print(f"   normal equations   : RMS offset error {r_alg:.4f} µT  pooled ratio {r_alg / crlb:.3f}"
              f"  per-trial ratio {n_alg:.3f}  mean error {np.round(col['d_alg'][sel].mean(axis=0), 3)} µT")
    n_out = col["n_out"]
    print(f"Grubbs removals on these clean runs: {int(n_out.sum())} samples in {int((n_out > 0).sum())} of {trials} runs")


if __name__ == "__main__":
    main()
