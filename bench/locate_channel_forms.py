"""Channel terms with lags, gains and nonlinear forms (``magcal.diagnose.locate.channel_forms``):
injected into simulated and real recordings at 2, 4 and 10× the recording's own floor, with
controls (the same recordings with the same channels and no effect).

    python3 bench/locate_channel_forms.py [--quick]

Each effect is added to the raw samples: a lagged current (delay or first-order, 0.3–1 s), a
temperature offset and a temperature gain (15–30 °C cycles), a current offset, a servo arm
(v₁ cos θ + v₂ sin θ of a logged angle) and a step at a threshold of a throttle. Size: the
largest offset the term adds (for a gain, F·|g|·max|ΔT|) is k × the floor, the RMS radial residual
of a plain ellipsoid on the clean recording. A real recording gets synthetic channels (it has
none). Printed per case: located (right effect and channel, lag within 30 %), the coefficient
within 30 % (20 % for the lag cases) as a vector and in size, the true size inside its 95 %
interval, a claim other than the truth, and on the controls any finding.

Real data: ../shared/data/real relative to the repository (override with MAGCAL_REAL_DATA) and
tests/data.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from magcal.app.load import load_series  # noqa: E402
from magcal.fit import fit_calibration  # noqa: E402
from magcal.diagnose.locate.base import Residual  # noqa: E402
from magcal.diagnose.locate import channel_forms as cf  # noqa: E402
from magcal.diagnose.locate.channel_report import reference  # noqa: E402
from magcal.diagnose.locate.channel_terms import delayed, low_passed  # noqa: E402
from magcal.sim.physics import Current, Motion, Physics, Scenario, Temperature  # noqa: E402

ROOT = Path(os.environ.get("MAGCAL_REAL_DATA", HERE.parent.parent / "shared" / "data" / "real"))
REAL = [
    HERE.parent / "tests/data/hmc5883l_sunsided_full_sphere_every3rd.csv",
    HERE.parent / "tests/data/lsm9ds1_ckexplorer_every4th.csv",
    HERE.parent / "tests/data/qmc5883l_tomisuarez_every5th_counts.csv",
    ROOT / "hmc5883l_sunsided/set-1_tilt-sphere_hmc5883l_mag.csv",
    ROOT / "gearvr_utzinger/mag_data.txt",
    ROOT / "magcal_ucalgary_example_hmc5843/mag.txt",
]


def residual(m, t, chans) -> Residual:
    """The residual a locator sees: the ellipsoid fitted to the samples, its floor, the noise."""
    fit = fit_calibration(m, model="ellipsoid", outliers=False)
    cal = fit.calibration
    r = np.linalg.norm(cal.correct(m), axis=1) - cal.field_ut
    noise = float(np.median(np.abs(np.diff(m, axis=0))) / 0.6745 / np.sqrt(2))
    return Residual(t, m, cal, noise, float(np.sqrt(np.mean(r**2))), chans)


def floor_of(m) -> tuple[float, np.ndarray, float]:
    fit = fit_calibration(m, model="ellipsoid", outliers=False)
    cal = fit.calibration
    r = np.linalg.norm(cal.correct(m), axis=1) - cal.field_ut
    return float(np.sqrt(np.mean(r**2))), np.asarray(cal.offset_ut), float(np.median(np.linalg.norm(m - cal.offset_ut, axis=1)))


def temp_cycle(t, rng):
    span = np.ptp(t)
    period = span / rng.uniform(1.2, 2.5)
    return 22.5 + 7.5 * np.sin(2 * np.pi * (t - t[0]) / period + rng.uniform(0, 2 * np.pi))


def current_pattern(t, rng):
    """On/off segments of 1–3 A lasting 1–5 s (a motor or a heater switching)."""
    c = np.zeros(len(t))
    s = t[0]
    while s < t[-1]:
        d = rng.uniform(1.0, 5.0)
        if rng.random() < 0.5:
            c[(t >= s) & (t < s + d)] = rng.uniform(1.0, 3.0)
        s += d
    return c


def servo_angle(t, rng):
    """A servo stepping to a new angle in −60…60° every 2–6 s, slewing at 120°/s."""
    target = np.zeros(len(t))
    s, a = t[0], 0.0
    while s < t[-1]:
        d = rng.uniform(2.0, 6.0)
        a = rng.uniform(-60, 60)
        target[(t >= s) & (t < s + d)] = a
        s += d
    out = target.copy()
    for i in range(1, len(t)):
        step = 120.0 * (t[i] - t[i - 1])
        out[i] = out[i - 1] + np.clip(target[i] - out[i - 1], -step, step)
    return out


def unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def inject(case, m, t, rng, k, floor, center, radius):
    """(samples with the effect, channels, truth dict)."""
    chans = {"temp_c": temp_cycle(t, rng), "current_a": current_pattern(t, rng)}
    if case == "control":
        if rng.random() < 0.5:
            chans["servo_angle_deg"] = servo_angle(t, rng)
        return m, chans, {}
    if case in ("current_delay", "current_first_order"):
        lag = rng.uniform(0.3, 1.0)
        c = chans["current_a"]
        x = delayed(c, t, lag) if case == "current_delay" else low_passed(c, t, lag)
        beta = unit(rng) * k * floor / np.max(np.abs(x))
        return m + np.outer(x, beta), chans, {"channel": "current_a", "coef": beta, "lag": lag, "effect": "lagged_channel"}
    if case == "temp_offset":
        c = chans["temp_c"]
        beta = unit(rng) * k * floor / np.max(np.abs(c - c.mean()))
        return m + np.outer(c - c.mean(), beta), chans, {"channel": "temp_c", "coef": beta, "effect": "temperature_drift"}
    if case == "current_offset":
        c = chans["current_a"]
        beta = unit(rng) * k * floor / np.max(c)
        return m + np.outer(c, beta), chans, {"channel": "current_a", "coef": beta, "effect": "current_interference"}
    if case == "temp_gain":
        c = chans["temp_c"]
        d = c - c.mean()
        g = k * floor / (radius * np.max(np.abs(d))) * rng.choice([-1, 1])
        # the gain is stated relative to the scale at the reference (the end value)
        g_ref = g / (1 + g * (reference("temp_c", c) - c.mean()))
        return center + (m - center) * (1 + g * d)[:, None], chans, {"channel": "temp_c", "gain": g_ref, "effect": "temperature_gain"}
    if case == "servo":
        th = servo_angle(t, rng)
        chans["servo_angle_deg"] = th
        v1, v2 = unit(rng), unit(rng)
        term = np.outer(np.cos(np.deg2rad(th)), v1) + np.outer(np.sin(np.deg2rad(th)), v2)
        term -= term.mean(axis=0)
        term *= k * floor / np.max(np.linalg.norm(term, axis=1))
        return m + term, chans, {"channel": "servo_angle_deg", "effect": "channel_angle"}
    raise ValueError(case)


def judge(found, truth):
    """(located: right channel, effect and lag within 30 %; vector coefficient within tol;
    magnitude within tol; truth inside the 95 % interval; a claim that is not the truth)."""
    if not truth:
        return False, False, False, False, bool(found)
    hit = [f for f in found if f.params.get("channel") == truth["channel"]]
    if not hit:
        return False, False, False, False, bool(found)
    f = hit[0]
    ok = f.effect == truth["effect"]
    if "lag" in truth:
        lag = f.where.get("lag_s")
        ok = ok and lag is not None and abs(lag - truth["lag"]) <= 0.3 * truth["lag"]
    vec = mag = inside = False
    tol = 0.2 if "lag" in truth else 0.3
    if "coef" in truth and "coef_magnitude_interval" in f.params:
        b, tb = np.asarray(f.params["coef_ut_per_unit"]), truth["coef"]
        vec = np.linalg.norm(b - tb) <= tol * np.linalg.norm(tb)
        mag = abs(np.linalg.norm(b) - np.linalg.norm(tb)) <= tol * np.linalg.norm(tb)
        lo, hi = f.params["coef_magnitude_interval"]
        inside = lo <= np.linalg.norm(tb) <= hi
    if "gain" in truth and "gain_per_unit" in f.params:
        g = float(np.mean(f.params["gain_per_unit"]))
        vec = mag = abs(g - truth["gain"]) <= tol * abs(truth["gain"])
        lo, hi = f.params["gain_low_pct_per_unit"][0], f.params["gain_high_pct_per_unit"][0]
        inside = lo <= 100 * truth["gain"] <= hi
    wrong = any(x.params.get("channel") != truth["channel"] for x in found) or not ok
    return bool(ok), bool(vec), bool(mag), bool(inside), bool(wrong)


def sim_recording(seed, n=3000):
    sc = Scenario(physics=Physics(hard_iron_ut=(12.0, -7.0, 4.0)), motion=Motion("sphere", period_s=20.0),
                  temperature=Temperature(), current=Current(), seed=seed)
    s = sc.simulate(n, 50.0).series
    return s.field_ut, s.t_s


def real_recording(path):
    s = load_series(path)
    m, t = s.field_ut[s.valid], s.t_s[s.valid]
    if len(m) > 6000:
        m = m[:: len(m) // 6000 + 1]
    t = np.arange(len(m)) / 50.0 if not s.clock else t[: len(m)] if len(t) == len(m) else np.arange(len(m)) / 50.0
    return m, t


def run(cases, sources, ks, seeds):
    rows = {}
    for name, (m0, t) in sources.items():
        floor, center, radius = floor_of(m0)
        for case in cases:
            for k in ks if case != "control" else [0]:
                for seed in seeds:
                    rng = np.random.default_rng(seed * 7919 + hash((name, case, k)) % 10007)
                    m, chans, truth = inject(case, m0, t, rng, k, floor, center, radius)
                    res = residual(m, t, chans)
                    found = cf.search(res)
                    verdict = judge(found, truth)
                    rows.setdefault((case, k), []).append(verdict)
                    if found and (case == "control" or not verdict[0]) and "--verbose" in sys.argv:
                        print(f"  {name} {case} k={k} seed={seed}: {[f.summary for f in found]} truth={truth}")
    return rows


def report(title, rows):
    print(f"\n{title}")
    for (case, k), r in sorted(rows.items()):
        a = np.array(r, dtype=float)
        if case == "control":
            print(f"  control             n={len(a):3d}  any finding {a[:, 4].mean():.3f}")
        else:
            print(f"  {case:19s} k={k:<3} n={len(a):3d}  located {a[:, 0].mean():.2f}  coef-vector {a[:, 1].mean():.2f}  "
                  f"coef-size {a[:, 2].mean():.2f}  in-95% {a[:, 3].mean():.2f}  other-claim {a[:, 4].mean():.2f}")


def logged_channels():
    """Real recordings with their own logged channels (die temperature; a flight controller's
    current, battery voltage and throttle): what the search says, with no effect added."""
    sys.path.insert(0, str(HERE))
    from real_channels import betaflight, umich_preflight

    print("\nreal recordings with their own channels (no effect added)")
    for source in (umich_preflight, betaflight):
        try:
            cases = list(source())
        except OSError as e:
            print(f"  {source.__name__}: not available ({e})")
            continue
        for label, s in cases:
            ok = s.valid & np.all(np.isfinite(s.field_ut), axis=1)
            for c in s.channels.values():
                ok &= np.isfinite(c)
            chans = {k: v[ok] for k, v in s.channels.items()}
            found = cf.search(residual(s.field_ut[ok], s.t_s[ok], chans))
            print(f"  {label} ({ok.sum()} samples, channels {', '.join(chans)}): "
                  + ("; ".join(f"{f.effect}: {f.summary}" for f in found) or "nothing claimed"))


def main():
    quick = "--quick" in sys.argv
    seeds = range(2 if quick else 3)
    ks = [4] if quick else [2, 4, 10]
    cases = ["control", "current_delay", "current_first_order", "temp_offset", "current_offset", "temp_gain", "servo"]
    t0 = time.time()
    sims = {f"sim{s}": sim_recording(500 + s) for s in range(2 if quick else 3)}
    report("simulated", run(cases, sims, ks, seeds))
    real = {p.name: real_recording(p) for p in REAL if p.exists()}
    report("real recordings", run(cases, real, ks, seeds))
    logged_channels()
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
