"""The data-fault screen (magcal.diagnose.locate.faults) on injected faults and on controls.

    python bench/locate_faults.py [--quick] [--seeds N]

Recordings: simulated (sphere and tilt motion, AK8975-quantised, some with glitches and a slow
offset wander) and the real raw recordings of ../shared/data/real (bench/real_recordings.py)
plus the excerpts in tests/data and the flight logs. Controls: every recording as it is, in full
(the screen must claim nothing), and 3 × --controls further clean simulations. Cases: each recording (at most MAX_N samples, evenly thinned)
with one fault injected at several placements and seeds:

- stuck_axis: one axis held at its value for 2–8 s (at most a tenth of the span);
- saturation: one axis, or all three, clipped at the value that leaves 3–10 % of samples beyond;
- axis_swap: a stretch of 5–15 % of the span read with two axes exchanged or one negated;
- repeated_timestamps / out_of_order_timestamps: five samples given the time of the one before,
  or five neighbouring pairs with their times exchanged.

Located: a finding of the injected kind on the right axis (and reading, for a swap) whose
stretch starts and ends within ±1 s or 5 % of the span of the truth (saturation: the right axis
and side); named: the kind is found at all; false: any finding that is not the injected fault.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import real_recordings  # noqa: E402

from magcal.app.load import load_series  # noqa: E402
from magcal.diagnose.locate.faults import TRANSFORMS, screen  # noqa: E402
from magcal.sim.physics import Motion, Physics, Scenario  # noqa: E402
from magcal.sim.wander import WanderComponent  # noqa: E402

MAX_N = 6000
TESTS_DATA = Path(__file__).resolve().parent.parent / "tests" / "data"
KINDS = ("stuck_axis", "saturation", "axis_swap", "repeated_timestamps", "out_of_order_timestamps")


def simulated(seeds: int) -> dict:
    out = {}
    for seed in range(seeds):
        for motion in (Motion("sphere", period_s=20.0), Motion("tilt", max_tilt_deg=50.0, period_s=15.0)):
            extra = {"glitch_rate": 0.002, "wander": (WanderComponent(0.5, tau_s=30.0),)} if seed % 2 else {}
            phys = Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3, **extra)
            run = Scenario(physics=phys, motion=motion, seed=100 + seed).simulate(3000, 50.0)
            out[f"sim_{motion.kind}_{seed}"] = (run.series.t_s, run.series.field_ut)
    return out


def sim_controls(seeds: int) -> int:
    """Clean simulations (whole sphere, tilts, flat turns; noise 0.2–1 µT; every other one with
    glitches and a slow offset wander): how many the screen claims anything on."""
    claimed = 0
    for seed in range(seeds):
        for motion in (Motion("sphere", period_s=20.0 + seed), Motion("tilt", max_tilt_deg=50.0, period_s=15.0),
                       Motion("yaw")):
            extra = {"glitch_rate": 0.003, "wander": (WanderComponent(0.5, tau_s=30.0),)} if seed % 2 else {}
            phys = Physics(hard_iron_ut=(21.0 + seed, -33.0, 8.0), noise_ut=0.2 + 0.02 * seed, **extra)
            run = Scenario(physics=phys, motion=motion, seed=500 + seed).simulate(2000, 50.0)
            found = screen(run.series.t_s, run.series.field_ut).found
            claimed += bool(found)
            for x in found:
                print(f"  sim seed {seed} {motion.kind}: {x.summary}")
    return claimed


def _files() -> list[tuple[Path, int | None]]:
    r = real_recordings.root()
    out = [(TESTS_DATA / f, None) for f in ("hmc5883l_sunsided_full_sphere_every3rd.csv", "lsm9ds1_ckexplorer_every4th.csv",
                                            "px4_esc_status_excerpt.ulg", "qmc5883l_tomisuarez_every5th_counts.csv")]
    out += [(TESTS_DATA / "ardupilot_log171_excerpt.bin", k) for k in (0, 1, 2)]
    out += [(TESTS_DATA / "px4_pyulog_sample_small_mags.ulg", k) for k in (0, 1)]
    out += [(r / "ardupilot_solo_log171" / "log171.bin", k) for k in (0, 1, 2)]
    out += [(r / p, None) for p in ("px4_cube_uavcan_esc/esc_status_log.ulg", "gearvr_utzinger/Officemag.txt",
                                    "qmc5883l_tomisuarez/noisy_raw_data.csv", "mpu9250_rm3100_umich_estibone/test1_esti.csv",
                                    "hmc5883l_sunsided/set-2_unmoved-with-x-pointing-forward-10min_hmc5883l_mag.csv")]
    return out


def real() -> dict:
    out = {k: (np.asarray(t, float), np.asarray(m, float))
           for k, (t, m) in real_recordings.available(real_recordings.RAW_LOADERS).items()}
    for path, k in _files():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                s = load_series(path, mag=k) if k is not None else load_series(path)
        except (OSError, ValueError):
            continue
        out[path.name + ("" if k is None else f"#{k}")] = (s.t_s, s.field_ut)
    return out


def inject(kind: str, t: np.ndarray, m: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray, dict]:
    t, m = t.copy(), m.copy()
    span = t[-1] - t[0]
    n = len(t)
    if kind == "stuck_axis":
        dur = min(rng.uniform(2.0, 8.0), 0.1 * span)
        t0 = rng.uniform(t[0] + 0.1 * span, t[-1] - 0.1 * span - dur)
        rows = np.flatnonzero((t >= t0) & (t <= t0 + dur))
        a = int(rng.integers(3))
        m[rows, a] = m[rows[0], a]
        return t, m, {"time_s": (t[rows[0]], t[rows[-1]]), "axis": "xyz"[a]}
    if kind == "saturation":
        axes = [0, 1, 2] if rng.uniform() < 0.3 else [int(rng.integers(3))]
        share, side = rng.uniform(0.03, 0.10), rng.choice([1.0, -1.0])
        for a in axes:
            rail = np.quantile(m[:, a], 1 - share if side > 0 else share)
            m[:, a] = np.minimum(m[:, a], rail) if side > 0 else np.maximum(m[:, a], rail)
        return t, m, {"axes": ["xyz"[a] for a in axes]}
    if kind == "axis_swap":
        dur = rng.uniform(0.05, 0.15) * span
        t0 = rng.uniform(t[0] + 0.05 * span, t[-1] - 0.05 * span - dur)
        rows = np.flatnonzero((t >= t0) & (t <= t0 + dur))
        name, perm, signs = TRANSFORMS[int(rng.integers(len(TRANSFORMS)))]
        m[rows] = m[rows][:, perm] * np.asarray(signs, float)
        return t, m, {"time_s": (t[rows[0]], t[rows[-1]]), "reading": name}
    at = 5 + 4 * rng.choice((n - 10) // 4, 5, replace=False)
    if kind == "repeated_timestamps":
        t[at] = t[at - 1]
    else:
        t[at], t[at + 1] = t[at + 1].copy(), t[at].copy()
    return t, m, {"n": 5}


def judge(kind: str, truth: dict, found, span: float) -> tuple[bool, bool, bool]:
    """(located, named, false claim)."""
    tol = max(1.0, 0.05 * span)
    mine = [x for x in found if x.effect == kind]
    ok = [x for x in mine if _matches(kind, truth, x, tol)]
    if kind == "saturation":
        hit_axes = {x.where.get("axis") for x in mine}
        located = set(truth["axes"]) <= hit_axes
        false = any(x.where.get("axis") not in truth["axes"] for x in mine)
    else:
        located, false = bool(ok), len(ok) < len(mine)
    false = false or any(x.effect != kind for x in found)
    return located, bool(mine), false


def _matches(kind, truth, x, tol) -> bool:
    if kind in ("repeated_timestamps", "out_of_order_timestamps"):
        return x.params["n_samples"] == truth["n"]
    if kind == "saturation":
        return x.where.get("axis") in truth["axes"]
    (a, b) = x.where["time_s"][0]
    near = abs(a - truth["time_s"][0]) <= tol and abs(b - truth["time_s"][1]) <= tol
    if kind == "stuck_axis":
        return near and x.where["axis"] == truth["axis"]
    return near and x.params["reading"] == truth["reading"]


def _thin(t, m):
    k = max(1, len(m) // MAX_N)
    return t[::k] - t[0], m[::k]


def run(recordings: dict, placements: int, label: str) -> None:
    print(f"\n== {label}: controls (each recording in full)")
    n_false = 0
    for name, (t, m) in recordings.items():
        found = screen(t, m).found
        n_false += bool(found)
        print(f"  {name[:44]:44s} n={len(t):6d}  claims: {[x.effect for x in found] or 'nothing'}")
    print(f"  controls with a claim: {n_false}/{len(recordings)}")
    rng = np.random.default_rng(7)
    print(f"== {label}: injected ({placements} placements each)")
    for kind in KINDS:
        tally = np.zeros(3, int)
        cases = 0
        for name, (t, m) in recordings.items():
            t, m = _thin(t, m)
            if len(t) < 100 or t[-1] - t[0] < 20.0 and kind == "stuck_axis":
                continue
            for _ in range(placements):
                ti, mi, truth = inject(kind, t, m, rng)
                tally += judge(kind, truth, screen(ti, mi).found, ti[-1] - ti[0])
                cases += 1
        print(f"  {kind:24s} cases {cases:4d}  located {tally[0] / cases:.3f}  named {tally[1] / cases:.3f}"
              f"  false {tally[2] / cases:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--controls", type=int, default=40, help="seeds of further clean simulations (three motions each)")
    ap.add_argument("--placements", type=int, default=3, help="placements per real recording and kind")
    args = ap.parse_args()
    t0 = time.time()
    run(simulated(2 if args.quick else args.seeds), 2 if args.quick else 4, "simulated")
    run(real(), 1 if args.quick else args.placements, "real")
    n = 4 if args.quick else args.controls
    print(f"\n== {3 * n} further clean simulations: {sim_controls(n)} with a claim")
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
