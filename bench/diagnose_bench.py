"""Benchmark of concealed effects for ``magcal diagnose``: detection, false alarms, coefficient
errors, glitch F1, timing and the 1 M-sample run.

    python3 bench/diagnose_bench.py [--seeds N] [--first-seed S] [--no-real] [--no-big]

Cases are drawn afresh from the seed (every parameter random within its stated range), so a
new ``--first-seed`` gives cases the detector has never seen.

Simulated (magcal.sim.physics.Scenario, AK8975-like, 5000 samples at 50 Hz, hard iron ±40 µT,
noise 0.3–0.6 µT, quantised):
  clean controls — sphere motion; with temperature and current columns but no effect; partial
  coverage (tilt ±25–45°); higher noise (0.8–1.2 µT);
  soft iron — symmetric distortion with largest gain deviation 0.5–2 %;
  temperature — |β| 0.05–0.12 µT/°C, a 15–25 °C peak-to-peak swing inside the recording;
  current — |κ| 0.25–1.2 µT/A on an intermittent 1–3 A channel;
  glitches — 4–15 µT, 0.2–0.9 % of samples;  drift — 0.8–3 µT over the recording;
  and pairs of these.
Real (../shared/data/real, see bench/real_recordings.py): each recording is first made a
sphere with its own ellipsoid fit and scaled to 50 µT (so its own soft iron is known to be
gone), then used with no injection but with unrelated temperature and current columns drawn
from the simulator, and with one effect injected. Truth for a real case is what the detector
reports on the plain corrected recording (a real recording may hold a real glitch or drift)
is neither required nor a false alarm; the injected effect must be found and nothing else.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
import warnings
import zlib
from pathlib import Path

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # one BLAS thread, set before numpy loads
    os.environ.setdefault(_name, "1")

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from magcal.core.series import Series  # noqa: E402
from magcal.diagnose import diagnose  # noqa: E402
from magcal.diagnose.model import Spec, fit_model  # noqa: E402
from magcal.sim.physics import Current, Motion, Physics, Scenario, Temperature  # noqa: E402

N = 5000
RATE = 50.0
CHANNEL_EFFECTS = {"temperature_drift": "temp_c", "current_interference": "current_a", "time_drift": "t_s"}


def _unit(rng):
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def _soft(rng, dev):
    """A symmetric distortion whose largest relative gain deviation is ``dev``."""
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    g = rng.uniform(-1, 1, 3)
    g -= g.mean()
    g *= dev / np.max(np.abs(g))
    return q @ np.diag(1 + g) @ q.T


def sim_case(kind: str, seed: int):
    rng = np.random.default_rng([seed, zlib.crc32(kind.encode())])
    dur = N / RATE
    phys = dict(hard_iron_ut=tuple(rng.uniform(-40, 40, 3)), noise_ut=float(rng.uniform(0.3, 0.6)))
    motion = Motion("sphere", period_s=float(rng.uniform(15, 30)))
    temp = Temperature()
    cur = Current()
    truth = {}
    parts = kind.split("+")
    for part in parts:
        if part == "clean":
            pass
        elif part == "channels":
            temp = Temperature(base_c=float(rng.uniform(15, 35)), swing_c=float(rng.uniform(15, 25)), period_s=dur / 1.3)
            cur = Current(level_a=float(rng.uniform(1, 3)), duty=float(rng.uniform(0.2, 0.6)))
        elif part == "partial":
            motion = Motion("tilt", max_tilt_deg=float(rng.uniform(25, 45)), period_s=float(rng.uniform(15, 30)))
        elif part == "noisy":
            phys["noise_ut"] = float(rng.uniform(0.8, 1.2))
        elif part == "soft":
            a = _soft(rng, float(rng.uniform(0.005, 0.02)))
            phys["distortion"] = tuple(map(tuple, a))
            truth["soft_iron"] = a
        elif part in ("softband", "softpartial"):
            # 1–2 % soft iron on a band of directions (level ±15–30°, yaw free) or a partial
            # sphere (±30–60°): the coverage on which nuisance harmonics used to soak it up
            lo, hi = (15, 30) if part == "softband" else (30, 60)
            motion = Motion("tilt", max_tilt_deg=float(rng.uniform(lo, hi)), period_s=float(rng.uniform(15, 30)))
            a = _soft(rng, float(rng.uniform(0.01, 0.02)))
            phys["distortion"] = tuple(map(tuple, a))
            truth["soft_iron"] = a
        elif part == "temp":
            temp = Temperature(base_c=float(rng.uniform(15, 35)), swing_c=float(rng.uniform(15, 25)), period_s=dur / 1.3)
            k = _unit(rng) * rng.uniform(0.05, 0.12)
            phys["temp_coef_ut_per_c"] = tuple(k)
            truth["temperature_drift"] = k
        elif part == "current":
            cur = Current(level_a=float(rng.uniform(1, 3)), duty=float(rng.uniform(0.2, 0.6)))
            k = _unit(rng) * rng.uniform(0.25, 1.2)
            phys["current_coef_ut_per_a"] = tuple(k)
            truth["current_interference"] = k
        elif part == "glitch":
            phys["glitch_rate"] = float(rng.uniform(0.002, 0.009))
            phys["glitch_ut"] = (4.0, 15.0)
            truth["outliers"] = None
        elif part == "drift":
            k = _unit(rng) * rng.uniform(0.8, 3.0) / dur
            phys["drift_ut_per_s"] = tuple(k)
            truth["time_drift"] = k
        else:
            raise ValueError(part)
    sc = Scenario(physics=Physics(**phys), motion=motion, temperature=temp, current=cur, seed=int(seed))
    run = sc.simulate(N, RATE)
    if "outliers" in truth:
        truth["outliers"] = set(int(i) for i in run.glitch_idx)
        if not truth["outliers"]:
            truth.pop("outliers")
    return run.series, truth


SIM_KINDS = [
    "clean", "clean+channels", "clean+partial", "clean+noisy",
    "soft", "temp", "current", "glitch", "drift",
    "soft+temp", "temp+glitch", "current+drift", "soft+current", "glitch+drift", "soft+glitch",
    "softband", "softpartial", "softband+temp", "softpartial+current",
]


# -- real recordings -----------------------------------------------------------------------------
def real_base(t, m):
    """The recording made a sphere of 50 µT by its own ellipsoid fit, plus a hard iron."""
    f = fit_model(m, {}, Spec(soft_iron=True))
    h = f.calibration().correct(m) * (50.0 / f.field_ut)
    return t - t[0], h + np.array([18.0, -27.0, 11.0])


def real_case(t, h, kind, seed):
    rng = np.random.default_rng([seed, zlib.crc32(kind.encode()), 7])
    dur = float(t[-1] - t[0]) or 1.0
    sc = Scenario(
        temperature=Temperature(base_c=float(rng.uniform(15, 35)), swing_c=float(rng.uniform(15, 25)), period_s=dur / 1.3),
        current=Current(level_a=float(rng.uniform(1, 3)), duty=0.4, segment_s=max(dur / 25, 0.5)),
        seed=int(seed),
    )
    temp = sc.temp_c(t)
    cur = sc.current_a(t)
    m = h.copy()
    truth = {}
    if kind == "soft":
        a = _soft(rng, float(rng.uniform(0.005, 0.02)))
        m = (h - h.mean(0)) @ a.T + h.mean(0)
        # soft iron acts on the field, not the hard iron: apply about the known hard iron
        m = (h - np.array([18.0, -27.0, 11.0])) @ a.T + np.array([18.0, -27.0, 11.0])
        truth["soft_iron"] = a
    elif kind == "temp":
        k = _unit(rng) * rng.uniform(0.05, 0.12)
        m = h + np.outer(temp - temp.mean(), k)
        truth["temperature_drift"] = k
    elif kind == "current":
        k = _unit(rng) * rng.uniform(0.25, 1.2)
        m = h + np.outer(cur, k)
        truth["current_interference"] = k
    elif kind == "glitch":
        nglitch = max(1, int(len(h) * rng.uniform(0.002, 0.009)))
        idx = rng.choice(np.arange(3, len(h) - 3), nglitch, replace=False)
        d = rng.standard_normal((nglitch, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        m[idx] += d * rng.uniform(4, 15, nglitch)[:, None]
        truth["outliers"] = set(int(i) for i in idx)
    elif kind == "drift":
        k = _unit(rng) * rng.uniform(0.8, 3.0) / dur
        m = h + np.outer(t - t.mean(), k)
        truth["time_drift"] = k
    return Series(t_s=t, field_ut=m, channels={"temp_c": temp, "current_a": cur}), truth


# -- scoring ---------------------------------------------------------------------------------------
def score(d, truth, intrinsic=frozenset()):
    found = d.to_dict()["findings"]
    names = {f["effect"] for f in found}
    expected = set(truth)
    # what a real recording itself holds is unknown: its own findings neither count as false
    # alarms nor are required
    judged = names - (set(intrinsic) - expected)
    out = {"exact": judged == expected, "found": sorted(judged), "expected": sorted(expected), "coef_err": {}, "glitch": None}
    for f in found:
        e = f["effect"]
        if e in truth and e in CHANNEL_EFFECTS:
            k = np.asarray(truth[e])
            out["coef_err"][e] = float(np.linalg.norm(np.array(f["params"]["coef_ut_per_unit"]) - k) / np.linalg.norm(k))
        if e == "soft_iron" and "soft_iron" in truth:
            w = np.linalg.inv(truth["soft_iron"])
            w *= 3 / np.trace(w)
            out["soft_err_pct"] = float(100 * np.max(np.abs(np.array(f["params"]["soft_iron"]) - w)))
    if "outliers" in truth:
        got = set()
        for f in found:
            if f["effect"] == "outliers":
                got = set(f["params"]["indices"])
        tr = truth["outliers"]
        fp = len(got - tr) if "outliers" not in intrinsic else 0  # real glitches are not false
        out["glitch"] = (len(got & tr), fp, len(tr - got))
    return out


def run_cases(cases):
    rows = []
    times = []
    for label, series, truth, intrinsic in cases:
        t0 = time.perf_counter()
        d = diagnose(series)
        dt = time.perf_counter() - t0
        if len(series) == N:
            times.append(dt)
        r = score(d, truth, intrinsic)
        r["label"] = label
        r["seconds"] = dt
        rows.append(r)
    return rows, times


def summarise(rows, title):
    print(f"\n== {title}: {len(rows)} cases")
    by = {}
    for r in rows:
        by.setdefault(r["label"].split("#")[0], []).append(r)
    print(f"{'case':<28}{'n':>4}{'exact set':>11}  false alarms / misses")
    for k, rs in by.items():
        fa = sum(len(set(r["found"]) - set(r["expected"])) for r in rs)
        miss = sum(len(set(r["expected"]) - set(r["found"])) for r in rs)
        bad = [f"{r['found']}" for r in rs if not r["exact"]][:2]
        print(f"{k:<28}{len(rs):>4}{np.mean([r['exact'] for r in rs]):>10.0%}   {fa} / {miss}  {' '.join(bad)}")
    exact = np.mean([r["exact"] for r in rows])
    clean = [r for r in rows if not r["expected"] or r["label"].startswith("clean")]
    silent = np.mean([not (set(r["found"]) - set(r["expected"])) for r in clean]) if clean else float("nan")
    errs = [v for r in rows for v in r["coef_err"].values()]
    tp = sum(r["glitch"][0] for r in rows if r["glitch"])
    fp = sum(r["glitch"][1] for r in rows if r["glitch"])
    fn = sum(r["glitch"][2] for r in rows if r["glitch"])
    f1 = 2 * tp / max(2 * tp + fp + fn, 1)
    print(f"exact effect set: {exact:.1%}   (target ≥ 95 %)")
    print(f"controls silent (no effect beyond the truth): {silent:.1%}   over {len(clean)} cases (target 100 %)")
    if errs:
        print(
            f"channel coefficient relative error: median {np.median(errs):.1%}, 95th pct {np.percentile(errs, 95):.1%}, "
            f"max {np.max(errs):.1%}, within 30 %: {np.mean(np.array(errs) <= 0.3):.1%}  ({len(errs)} coefficients)"
        )
    soft = [r["soft_err_pct"] for r in rows if "soft_err_pct" in r]
    if soft:
        print(f"soft-iron matrix max abs error: median {np.median(soft):.3f} %, max {np.max(soft):.3f} % of unit gain")
    print(f"glitch precision {tp / max(tp + fp, 1):.3f} recall {tp / max(tp + fn, 1):.3f} F1 {f1:.3f}   (target F1 ≥ 0.8; tp {tp} fp {fp} fn {fn})")
    return exact


def _stated_floor(t, h, series, kind):
    """The slow-term floor ``diagnose`` states on the plain recording with this case's own
    channels (no injection), for the injected kind's channel; None when it states none."""
    d = diagnose(Series(t_s=t, field_ut=h, channels=dict(series.channels)))
    chan = "temp_c" if kind == "temp" else "t_s"
    for lim in d.to_dict()["limits"]:
        if chan in lim.get("slow_term_floor_ut_per_unit", {}):
            lo_hi = lim.get("slow_term_floor_range_ut_per_unit", {}).get(chan, (None, None))
            return (lim["slow_term_floor_ut_per_unit"][chan], *lo_hi)
    return None


def _floor_summary(slow, rows):
    """Injected temperature and drift cases split by the floor the plain recording states: does
    the detector find what it says it could, and stay silent on what it says it could not?"""
    def size(tr):
        return np.linalg.norm(next(iter(tr.values())))

    def pick(test):
        return [(lab, rows[lab]) for lab, f, tr in slow if f is not None and test(size(tr), *f)]

    def found(rs):
        return sum(1 for _, r in rs if set(r["expected"]) <= set(r["found"]))

    above, below = pick(lambda k, f, lo, hi: k >= f), pick(lambda k, f, lo, hi: k < f)
    well = pick(lambda k, f, lo, hi: k >= 2 * f)
    over_hi = pick(lambda k, f, lo, hi: hi is not None and k >= hi)
    under_lo = pick(lambda k, f, lo, hi: lo is not None and k < lo)
    none = [lab for lab, f, _ in slow if f is None]
    print(f"injected temperature / drift against the floor diagnose states on the plain recording (same channels): "
          f"above it {found(above)} of {len(above)} found ({found(well)} of {len(well)} at twice it or more), "
          f"below it {found(below)} of {len(below)} found; above the upper end of its range by direction "
          f"{found(over_hi)} of {len(over_hi)}, below the lower end {found(under_lo)} of {len(under_lo)}"
          + (f"; {len(none)} with no floor stated (no wander limit)" if none else ""))


def big_run(n: int) -> dict:
    """1 M samples in a fresh process: wall time of diagnose() and the process's peak memory."""
    code = f"""
import resource, time, json, sys, warnings
sys.path.insert(0, {str(HERE.parent)!r})
warnings.filterwarnings('ignore')
from magcal.sim.physics import Scenario, Physics, Temperature, Current
from magcal.diagnose import diagnose
sc = Scenario(physics=Physics(hard_iron_ut=(20,-30,10), temp_coef_ut_per_c=(0.06,0.04,-0.05), glitch_rate=0.002),
              temperature=Temperature(swing_c=20, period_s=15000), current=Current(level_a=2), seed=5)
s = sc.simulate({n}, 50.0).series
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0, c0 = time.perf_counter(), time.process_time(); d = diagnose(s); dt, dc = time.perf_counter() - t0, time.process_time() - c0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps(dict(seconds=dt, cpu_seconds=dc, peak_mb=peak / 1024, before_mb=before / 1024, effects=d.effects)))
"""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def thread_timing(runs: int = 9) -> dict:
    """diagnose() on a 5000-sample simulated recording in fresh processes, with OpenBLAS left at
    its default (a thread per core) and with one thread: median CPU and wall seconds each."""
    code = f"""
import json, sys, time, warnings
sys.path.insert(0, {str(HERE.parent)!r})
warnings.filterwarnings('ignore')
import numpy as np
from magcal.sim.physics import Scenario, Physics, Temperature, Current
from magcal.diagnose import diagnose
s = Scenario(physics=Physics(hard_iron_ut=(20,-30,10), distortion=((1.015,0.004,0),(0.004,0.99,0),(0,0,0.995))),
             temperature=Temperature(swing_c=20, period_s=60), current=Current(level_a=2), seed=5).simulate({N}, 50.0).series
diagnose(s)
cpu, wall = [], []
for _ in range({runs}):
    c0, w0 = time.process_time(), time.perf_counter(); diagnose(s)
    cpu.append(time.process_time() - c0); wall.append(time.perf_counter() - w0)
print(json.dumps(dict(cpu=float(np.median(cpu)), wall=float(np.median(wall)))))
"""
    out = {}
    for label, threads in (("default threads", None), ("one thread", "1")):
        env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
        if threads:
            env.update(OPENBLAS_NUM_THREADS=threads, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
        out[label] = json.loads(res.stdout.strip().splitlines()[-1])
    return out


def command_timing(runs: int = 5) -> dict:
    """The whole ``magcal diagnose FILE --json`` on a 5000-sample CSV (start-up included):
    median wall and CPU (user + system of the child) seconds."""
    import tempfile

    from magcal.recordings.table import save_csv

    s, _ = sim_case("soft+temp", 7)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rec.csv"
        save_csv(s, path)
        wall, cpu = [], []
        for _ in range(runs):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "magcal", "diagnose", str(path), "--json"], capture_output=True, check=True,
                           cwd=str(HERE.parent))
            wall.append(time.perf_counter() - t0)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return {"wall": float(np.median(wall)), "cpu": float(np.median(cpu))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=8, help="cases per simulated kind (default 8)")
    ap.add_argument("--first-seed", type=int, default=20261122)
    ap.add_argument("--real-seeds", type=int, default=2, help="injections per real recording and kind")
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--no-big", action="store_true")
    ap.add_argument("--real-max", type=int, default=8000, help="truncate real recordings to this many samples")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")

    cases = []
    for kind in SIM_KINDS:
        for j in range(args.seeds):
            s, truth = sim_case(kind, args.first_seed + 1000 * j)
            cases.append((f"sim {kind}#{j}", s, truth, {}))
    rows, times = run_cases(cases)
    summarise(rows, "simulated")
    all_rows = list(rows)

    if not args.no_real:
        import real_recordings as rr

        rcases = []
        slow = []  # (label, the floor the plain recording states for the injected kind, truth)
        for name, (t, m) in rr.available().items():
            t, m = t[: args.real_max], m[: args.real_max]
            t, h = real_base(t, m)
            intrinsic = {f.effect for f in diagnose(Series(t_s=t, field_ut=h)).findings}
            for kind in ("none", "soft", "temp", "current", "glitch", "drift"):
                for j in range(args.real_seeds):
                    s, truth = real_case(t, h, kind, args.first_seed + 31 * j)
                    intr = set(intrinsic) - ({"time_drift"} if kind == "drift" else set())
                    rcases.append((f"real {name} {kind}#{j}", s, truth, frozenset(intr)))
                    if kind in ("temp", "drift"):
                        slow.append((f"real {name} {kind}#{j}", _stated_floor(t, h, s, kind), truth))
            print(f"real {name}: {len(m)} samples; intrinsic findings of the corrected recording: {sorted(intrinsic) or 'none'}")
        rrows, _ = run_cases(rcases)
        summarise(rrows, "real recordings (one effect injected, or none)")
        _floor_summary(slow, {r["label"]: r for r in rrows})
        all_rows += rrows

    summarise(all_rows, "all cases")
    threads = thread_timing()
    for label, r in threads.items():
        print(f"diagnose() on {N} samples, OpenBLAS {label}: median {r['cpu'] * 1000:.0f} ms CPU, {r['wall'] * 1000:.0f} ms wall")
    cmd = command_timing()
    print(f"magcal diagnose FILE --json ({N} samples, start-up included): median {cmd['wall']:.2f} s wall, "
          f"{cmd['cpu']:.2f} s CPU (target 0.4 s)")
    print(f"\ntiming: diagnose() on {N}-sample recordings: median {np.median(times) * 1000:.0f} ms, "
          f"95th pct {np.percentile(times, 95) * 1000:.0f} ms over {len(times)} runs (target median ≤ 150 ms)")
    if not args.no_big:
        big = big_run(1_000_000)
        print(f"1 M samples: diagnose() {big['seconds']:.1f} s wall, {big['cpu_seconds']:.1f} s CPU (target ≤ 30 s); process peak RSS {big['peak_mb']:.0f} MB "
              f"(of which {big['before_mb']:.0f} MB held the simulated recording before diagnosis; target ≤ 1 GB); "
              f"found {big['effects']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
