"""How well ``narrowband_line`` finds a sinusoid added to the sensor axes, and how often it
claims one that is not there.

    python bench/locate_lines.py [--quick] [--seeds N]

Cases: simulated recordings (sphere, tilt and yaw motions; noise 0.2–1 µT; 50 and 100 Hz
sampling with timestamp jitter) and the real raw recordings of ../shared/data/real (via
bench/real_recordings.py, at most MAX_N samples each). Each gets a line at 2, 4 and 10× its own
floor (the RMS radial residual of a plain ellipsoid on the clean samples) on one axis or along a
random direction, at a random apparent frequency or at the alias of 50/60 Hz mains by a clock
off its nominal rate; the same recording without the line is the control. The calibration
searched is ``magcal fit``'s own on the samples as they are.

Printed per group: located (a line within 2 % of the injected frequency on the right axes),
named (a narrowband_line reported at all), false (a line reported at another frequency; on a
control, any line), and the amplitude error of located lines.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import real_recordings  # noqa: E402

from magcal.core.sample import UT_PER_COUNT, asa_gain  # noqa: E402
from magcal.diagnose.locate import lines  # noqa: E402
from magcal.diagnose.locate.base import Residual  # noqa: E402
from magcal.diagnose.locate.step import floor_of  # noqa: E402
from magcal.fit import fit_calibration  # noqa: E402
from magcal.sim.physics import Motion, Physics, Scenario  # noqa: E402

MAX_N = 6000
FACTORS = (2.0, 4.0, 10.0)


def simulated(seed: int, motion: str, noise_ut: float, rate_hz: float, n: int, jitter_s: float):
    sc = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=noise_ut),
                  motion=Motion(motion, max_tilt_deg=40.0), seed=seed)
    k = np.arange(n)
    t = np.sort(k / rate_hz + np.random.default_rng(seed).normal(0.0, jitter_s, n))
    m, _ = sc.field_ut(t, k)
    raw, _ = sc.to_counts(m)
    return t, raw * UT_PER_COUNT * np.array([asa_gain(a) for a in sc.physics.asa]), sc.physics.truth()


def recordings(quick: bool, seeds: int):
    out = {}
    motions = ("sphere", "tilt", "yaw")
    for s in range(seeds):
        for j, motion in enumerate(motions):
            rate = (50.0, 100.0)[(s + j) % 2]
            noise = (0.2, 0.5, 1.0)[(s + 2 * j) % 3]
            out[f"sim_{motion}_{rate:.0f}hz_{noise}ut_s{s}"] = simulated(100 + 7 * s + j, motion, noise, rate, 3000, 0.4e-3)
    real = real_recordings.available(real_recordings.RAW_LOADERS)
    for name, (t, m) in sorted(real.items())[: 4 if quick else None]:
        t, m = np.asarray(t, float), np.asarray(m, float)
        k = max(1, len(m) // MAX_N)
        t, m = t[::k], m[::k]
        if name in real_recordings.UNKNOWN_UNIT:
            m = m * 50.0 / np.median(np.linalg.norm(m - m.mean(0), axis=1))
        good = np.all(np.isfinite(m), axis=1) & np.isfinite(t)
        order = np.argsort(t[good], kind="stable")
        out["real_" + name] = (t[good][order], m[good][order], None)
    return out


def search(t, m, truth=None):
    """The search on ``magcal fit``'s calibration; on flat turns (no calibration can be fitted,
    yet a line is still there to find) on the truth's."""
    result = fit_calibration(m) if truth is None else None
    cal = result.calibration if result else truth
    if cal is None:
        return None
    res = Residual(t, m, cal, 0.0, floor_of(m), {})
    return lines.search(res)


def extra_controls(group, t, m):
    """More real controls: each half of a real recording on its own calibration."""
    if group != "real":
        return []
    h = len(t) // 2
    return [(f" half {i + 1}", search(t[sl], m[sl])) for i, sl in enumerate((slice(0, h), slice(h, None)))]


def injection(rng, t, floor, factor):
    """(the line added to the raw samples, its frequency, its axes)."""
    dt = float(np.median(np.diff(t)))
    span = t[-1] - t[0]
    lo, hi = max(15.0 / span, 0.2), 0.45 / dt
    if rng.random() < 0.4:  # mains aliased by a clock a little off its nominal rate
        clock = (1.0 / dt) * (1 + rng.uniform(-0.06, 0.06))
        src = rng.choice([50.0, 60.0, 100.0, 120.0])
        f = abs(src - clock * round(src / clock))
        if not lo <= f <= hi:
            f = rng.uniform(lo, hi)
    else:
        f = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    if rng.random() < 0.6:
        axis = int(rng.integers(3))
        vec = np.eye(3)[axis]
        axes = ["xyz"[axis]]
    else:
        vec = rng.normal(size=3)
        vec /= np.linalg.norm(vec)
        axes = None  # direction: judged on the direction
    wave = factor * floor * np.outer(np.cos(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)), vec)
    return wave, f, axes, vec


def judge_case(found, f, axes, vec):
    if found is None:
        return dict(located=False, named=False, false=False, amp_err=np.nan)
    near = [x for x in found if abs(x.params["frequency_hz"] - f) <= 0.02 * f]
    others = [x for x in found if x not in near]
    ok = False
    amp_err = np.nan
    if near:
        x = near[0]
        got = x.where["axis"] if isinstance(x.where["axis"], list) else [x.where["axis"]]
        if axes is not None:
            ok = sorted(got) == sorted(axes)
        else:
            ok = abs(float(np.dot(x.where["direction"], vec))) > 0.9
        amp_err = float(np.linalg.norm(x.params["amplitude_ut"]))
    return dict(located=ok, named=bool(near), false=bool(others), amp_err=amp_err)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--placements", type=int, default=2)
    args = ap.parse_args(argv)
    recs = recordings(args.quick, args.seeds)
    tally = defaultdict(lambda: defaultdict(list))
    timing = []
    for name, (t, m, truth) in recs.items():
        truth = truth if "_yaw_" in name else None
        group = "sim" if name.startswith("sim") else "real"
        floor = floor_of(m)
        if not np.isfinite(floor) and truth is not None:  # flat turns: no ellipsoid; the truth's own residual
            floor = float(np.sqrt(np.mean((np.linalg.norm(truth.correct(m), axis=1) - truth.field_ut) ** 2)))
        t0 = time.perf_counter()
        found = search(t, m, truth)
        timing.append(time.perf_counter() - t0)
        for part, found in [("", found)] + extra_controls(group, t, m):
            tally[group + " control"]["false"].append(bool(found))
            if found:
                print(f"  control claim {name}{part}: {[x.summary for x in found]}")
        rng = np.random.default_rng(abs(hash(name)) % 2**32)
        for factor in FACTORS:
            for _ in range(args.placements):
                wave, f, axes, vec = injection(rng, t, floor, factor)
                true_amp = factor * floor * np.abs(vec)
                found = search(t, m + wave, truth)
                j = judge_case(found, f, axes, vec)
                key = f"{group} {factor:g}x"
                for k_, v in j.items():
                    if k_ == "amp_err":
                        if np.isfinite(v):
                            tally[key]["amp_rel_err"].append(abs(v - np.linalg.norm(true_amp)) / np.linalg.norm(true_amp))
                    else:
                        tally[key][k_].append(v)
                if not j["located"] or j["false"]:
                    said = [(round(x.params["frequency_hz"], 3), x.where["axis"]) for x in found or ()]
                    print(f"  missed {name} {factor:g}x f={f:.3f} axes={axes}: {said}")
    print(f"{'group':<16}{'cases':>6}{'located':>9}{'named':>7}{'false':>7}{'|amp| err':>10}")
    for key in sorted(tally):
        d = tally[key]
        n = len(d["false"])
        loc = np.mean(d["located"]) if d["located"] else float("nan")
        nam = np.mean(d["named"]) if d["named"] else float("nan")
        amp = np.median(d["amp_rel_err"]) if d["amp_rel_err"] else float("nan")
        print(f"{key:<16}{n:>6}{loc:>9.3f}{nam:>7.3f}{np.mean(d['false']):>7.3f}{amp:>10.3f}")
    print(f"search time per recording: median {np.median(timing):.2f} s, max {np.max(timing):.2f} s")


if __name__ == "__main__":
    main()
