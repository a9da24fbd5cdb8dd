"""The daemon's drift monitor on twins of real recordings, beside the white-noise simulator.

Nothing changes in these streams, so every alarm is false; the monitor states a false-alarm
probability of ``alpha`` per test window (the daemon's defaults: 500-sample windows,
alpha = 0.001, 8 baseline windows). For each real recording with motion: the sensor model
learned from it (as ``magcal diagnose --model-out`` writes it), simulated on the simulator's own
motion (as ``magcal simulate --model`` does) for ``--minutes``, fed to a DriftMonitor holding
the model's own calibration; beside it the same model with its wander replaced by white noise
of the same total size (the white-noise simulator). Printed: test windows, alarms, the rate
against alpha, and the monitor's own estimates of the spread it allows (φ the factor on the
noise part, q the sensor's own offset wander, µT rms per direction) at the end of the stream.

Detection: for each stream a shorter one (40 windows) of the same sensor gets a new hard iron
of each ``--step-ut`` size in a random direction at a random sample after window 16; counted
as caught when the window holding the step or the next one alarms.

Run: MAGCAL_REAL_DATA=… python bench/twin_monitor.py [--minutes 20] [--streams 3] [--seed N]
     [--step-ut 1,3] [--only NAME]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402

import twin_recordings as tr  # noqa: E402
from magcal.app.config import DaemonSettings  # noqa: E402
from magcal.diagnose import twin  # noqa: E402
from magcal.fit import fit_calibration as fit  # noqa: E402
from magcal.logic.monitor import DriftMonitor, Phase  # noqa: E402
from magcal.sim.physics import Motion, Physics, Scenario  # noqa: E402

BASELINE_WINDOWS = 8


def white_twin(model):
    """The same sensor with its wander (offset and field) folded into white noise of the same
    variance, and no disturbances: the white-noise simulator."""
    extra = sum(np.asarray(c.sigma_ut) ** 2 for c in model.wander)
    noise = np.sqrt(np.asarray(model.noise_ut) ** 2 + extra)
    return dataclasses.replace(model, wander=(), disturbances=None, noise_ut=tuple(noise))


def _field(model, seed, n):
    rate = min(model.rate_hz, 100.0)
    sc = Scenario(physics=Physics(field_ut=model.calibration.field_ut), motion=Motion("sphere", period_s=20.0),
                  seed=seed, model=model)
    return sc.simulate(n, rate).series.only_valid().field_ut


def run_stream(model, seed, minutes, window, alpha):
    s_field = _field(model, seed, int(minutes * 60 * min(model.rate_hz, 100.0)))
    mon = DriftMonitor(model.calibration, window, alpha, BASELINE_WINDOWS)
    verdicts = [v for v in mon.add(s_field) if v.phase is Phase.TEST]
    st = mon.status()
    return np.array([v.p_value for v in verdicts]), st["dispersion_factor"], st["offset_wander_ut"]


STEP_WINDOWS = 40  # windows per detection stream: the baseline, then a step somewhere in 16..35


def detects(model, seed, step_ut, window, alpha) -> bool:
    """A new hard iron of ``step_ut`` µT in a random direction, at a random sample after the
    baseline and a stretch of tests: does the monitor alarm in the window holding the step or
    the next one?"""
    rng = np.random.default_rng([seed, 0x57E9])
    m = _field(model, seed, STEP_WINDOWS * window).copy()
    at = int(rng.integers(16 * window, 36 * window))
    direction = rng.normal(size=3)
    m[at:] += step_ut * direction / np.linalg.norm(direction)
    mon = DriftMonitor(model.calibration, window, alpha, BASELINE_WINDOWS)
    verdicts = mon.add(m)
    return any(v.drifted for v in verdicts[at // window: at // window + 2])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=20.0)
    p.add_argument("--streams", type=int, default=3, help="twin streams per recording")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--only", default=None)
    p.add_argument("--step-ut", default="1,3", help="hard-iron steps (µT, comma-separated) whose detection is counted")
    args = p.parse_args(argv)
    steps = [float(x) for x in args.step_ut.split(",") if x]
    cfg = DaemonSettings()
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little")
    print(f"monitor: window {cfg.monitor_window}, alpha {cfg.monitor_alpha}, {BASELINE_WINDOWS} baseline windows; "
          f"{args.streams} streams × {args.minutes:g} min per recording; first seed {seed}")
    totals = {"twin": [], "white": []}
    caught = {(label, st): [] for label in totals for st in steps}
    for k, name in enumerate(tr.RECORDINGS):
        if (args.only and args.only not in name) or "still" in name:
            continue
        series, _ = tr.load(name)
        r = fit(series.field_ut, model="auto")
        if not r:
            continue
        model = twin.learn(series.only_valid(), r.calibration)
        line = f"{name:<40}"
        for label, mdl in (("twin", model), ("white", white_twin(model))):
            ps = []
            for j in range(args.streams):
                p_, phi, q = run_stream(mdl, seed + 1000 * k + j, args.minutes, cfg.monitor_window, cfg.monitor_alpha)
                ps.append(p_)
                for st in steps:
                    caught[(label, st)].append(detects(mdl, seed + 1000 * k + j, st, cfg.monitor_window,
                                                       cfg.monitor_alpha))
            ps = np.concatenate(ps)
            totals[label].append(ps)
            line += f"  {label}: {_rates(ps)} (φ {phi:5.1f}, q {q:4.2f} µT)"
        print(line)
        sys.stdout.flush()
    for label, ps in totals.items():
        ps = np.concatenate(ps) if ps else np.array([])
        print(f"all {label:>5}: {len(ps)} test windows; p < level at levels {LEVELS}: {_rates(ps)}")
    for (label, st), hits in caught.items():
        print(f"new hard iron of {st:g} µT, {label:>5}: caught within two windows in {sum(hits)} of {len(hits)} streams")
    return 0


LEVELS = (0.001, 0.01, 0.05)


def _rates(ps) -> str:
    """Share of test windows whose p-value is below each level (a monitor that holds its
    stated rate gives about the level itself)."""
    return " ".join(f"{np.mean(ps < a):.4f}" if len(ps) else "-" for a in LEVELS) + f" of {len(ps)}"


if __name__ == "__main__":
    sys.exit(main())
