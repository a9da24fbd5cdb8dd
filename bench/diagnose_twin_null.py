"""``diagnose``'s false alarms on twins of real recordings, beside the white-noise simulator.

    python3 bench/diagnose_twin_null.py [--draws N] [--first-seed S] [--max-samples M] [--only NAME,NAME]
                                           [--without-f-alone] [--by-effect]

For every real recording with motion (bench/twin_recordings.py: at least 1000 samples; the still
takes are left out, they determine no calibration): its sensor twin is learned around fit's
calibration (``magcal.diagnose.twin.learn``, what ``diagnose --model-out`` writes), without
its channel terms and temperature gain, and drawn ``--draws`` times on the recording's own
times and field directions (recovered through the inverse model: ``simulate --like``). Each draw
gets fresh synthetic channels unrelated to it (a temperature swing, an intermittent current and
a phase-randomised copy of one of them, as bench/diagnose_raw.py draws them) and is diagnosed
with the defaults. Nothing in a draw follows any channel or time, so every channel or drift
finding is a false alarm; ``diagnose`` states a family-wise false-alarm rate of alpha = 0.01
per recording.

Beside each twin: the same draws diagnosed with the tests referred to the F distribution alone
(``diagnose(..., twin_null=False)``, white noise as the null: what the twin changes), and the
same model with its offset wander folded into white noise of the same variance (the white-noise
simulator), diagnosed as usual. Printed per recording: the twin's wander and the draws with a
false alarm in each of the three, then the overall rates against alpha. The rates count the
catalogue's channel and drift effects; a term the locate step keeps on one of the draw's channels
or on time (a lagged or curved channel, ``lagged_channel``) is a false alarm too, and the draws
where it is the only one are counted beside them. ``--by-effect`` prints each false alarm and
what judged it. A new ``--first-seed`` gives draws never seen.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402

import twin_recordings as tr  # noqa: E402
from diagnose_raw import EFFECT, channels_for  # noqa: E402
from magcal.core.series import Series  # noqa: E402
from magcal.diagnose import diagnose, twin  # noqa: E402
from magcal.diagnose.ladder import ALPHA  # noqa: E402
from magcal.fit import fit_calibration  # noqa: E402
from twin_monitor import white_twin  # noqa: E402


def bare(model):
    """The twin without its channel terms and temperature gain: nothing in a draw follows a
    channel, whatever channels it is diagnosed with."""
    for c in list(model.calibration.coef_ut_per_unit):
        model = model.without(c)
    return model.without("temperature_gain")


def false_alarms(model, u, t, seed: int, twin_null: bool = True) -> list:
    """Channel or drift findings on one draw of ``model`` with fresh unrelated channels
    (``twin_null``: diagnose's own; False: its tests referred to the F distribution alone), each
    (effect, channel, what judged it); the catalogue's effects first (what the rates count), then
    the locate step's terms on the draw's channels or time (a lagged or curved channel)."""
    rng = np.random.default_rng([seed, 0x7E1])
    m, valid = model.simulate(u, t, None, seed)
    chans = channels_for(t, rng, seed, "current_a" if rng.uniform() < 0.5 else "temp_c")
    s = Series(t_s=t[valid], field_ut=m[valid], channels={c: v[valid] for c, v in chans.items()})
    d = diagnose(s, twin_null=twin_null)
    ours = set(chans) | {"t_s"}
    out = [(f.effect, f.where.get("channel"), judged(f, d.tests)) for f in d.findings if f.effect in EFFECT.values()]
    return out + [(f.effect, f.where.get("channel"), judged(f, d.tests)) for f in d.findings
                  if f.effect not in EFFECT.values() and f.where.get("channel") in ours]


def judged(f, tests: dict) -> str:
    """What let a finding through: the catalogue's test (p, the twin's λ, Holm's family size,
    the first step's α/m) or the locate step's channel search (score against its threshold, the
    largest score of the circularly shifted channel, and how many shifts)."""
    ev = f.evidence
    if "p_value" in ev:
        m = tests.get("n_tests", 0)
        return (f"F {ev['F']:.1f} p {ev['p_value']:.1e} λ {ev.get('twin_inflation', 1.0):.2f} "
                f"family {m} (α/m {ALPHA / max(m, 1):.1e})" + (" replaced by a located term" if "replaces" in ev else ""))
    if "threshold" in ev and "score" in ev:
        clean = " (the threshold below the raw shifts' largest: set by the null without the term)" \
            if ev["threshold"] < ev.get("null_max", 0.0) else ""
        return f"score {ev['score']:.1f} threshold {ev['threshold']:.1f} shifts' largest {ev.get('null_max', float('nan')):.1f} " \
               f"of {ev.get('n_shifts', 0)}{clean}" + (f", in place of the catalogue's {ev['replaces'].get('effect')}"
                                                       if isinstance(ev.get("replaces"), dict) else "")
    return ", ".join(f"{k} {v}" for k, v in ev.items() if isinstance(v, (int, float)))[:160]


def recordings(only: str | None, max_samples: int):
    """(k, name, model, u, t) for every recording with motion that fit can calibrate; ``only``:
    comma-separated parts of names, the others skipped. k is the recording's place among those
    with motion, so a recording's draws (seed + 1000·k) are the same with or without ``only``."""
    wanted = [w.strip() for w in only.split(",")] if only else []
    moving = [name for name in tr.RECORDINGS if "still" not in name]
    for k, name in enumerate(moving):
        if wanted and not any(w in name for w in wanted):
            continue
        series, fixed = tr.load(name)
        if fixed is not None:
            continue
        s = series.only_valid()
        s = Series(t_s=s.t_s[:max_samples] - s.t_s[0], field_ut=s.field_ut[:max_samples])
        r = fit_calibration(s.field_ut, model="auto")
        if not r:
            continue
        model = bare(twin.learn(s, r.calibration))
        yield k, name, model, model.directions_of(s.field_ut), s.t_s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=8, help="twin draws per recording (default 8)")
    ap.add_argument("--first-seed", type=int, default=None, help="default: fresh from the OS")
    ap.add_argument("--max-samples", type=int, default=8000)
    ap.add_argument("--only", default=None, help="comma-separated parts of recording names (each keeps its full-run seeds)")
    ap.add_argument("--without-f-alone", action="store_true",
                    help="skip the F-alone column (it uses no twin: what the twin learns cannot change it)")
    ap.add_argument("--by-effect", action="store_true",
                    help="print every false alarm: recording, draw, effect, channel and what judged it")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    seed0 = args.first_seed if args.first_seed is not None else int.from_bytes(os.urandom(4), "little")
    print(f"diagnose on twins of real recordings: {args.draws} draws each, first seed {seed0}, alpha {ALPHA} "
          "(family-wise, per recording)")
    print(f"{'recording':<44}{'n':>6}{'wander µT (parts)':>28}{'twin FA':>10}{'F alone':>10}{'white FA':>10}{'CPU s':>7}")
    totals = {"twin": [0, 0], "F alone": [0, 0], "white": [0, 0]}
    located = {label: 0 for label in totals}  # draws whose only false alarm is the locate step's
    for k, name, model, u, t in recordings(args.only, args.max_samples):
        c0 = time.process_time()
        line = {}
        for label, mdl, own in (("twin", model, True), ("F alone", model, False), ("white", white_twin(model), True)):
            if label == "F alone" and args.without_f_alone:
                line[label] = "-"
                continue
            alarms = [false_alarms(mdl, u, t, seed0 + 1000 * k + j, own) for j in range(args.draws)]
            hits = [any(a[0] in EFFECT.values() for a in draw) for draw in alarms]
            located[label] += sum(any(a[0] not in EFFECT.values() for a in draw) and not h for draw, h in zip(alarms, hits))
            if args.by_effect:
                for j, draw in enumerate(alarms):
                    for effect, channel, why in draw:
                        print(f"  {label}: {name} draw {j} (seed {seed0 + 1000 * k + j}): {effect} on {channel}: {why}")
            totals[label][0] += sum(hits)
            totals[label][1] += len(hits)
            line[label] = f"{sum(hits)}/{len(hits)}"
        wander = f"{np.sqrt(sum(c.variance for c in model.wander)):.2f} ({len(model.wander)} parts)" if model.wander else "none"
        per = (time.process_time() - c0) / ((2 if args.without_f_alone else 3) * args.draws)
        print(f"{name[:43]:<44}{len(t):>6}{wander[:27]:>28}{line['twin']:>10}{line['F alone']:>10}{line['white']:>10}{per:>7.2f}",
              flush=True)
    for label, (fa, n) in totals.items():
        if not n:
            continue
        rate = fa / n if n else float("nan")
        print(f"all {label:>7}: {fa}/{n} draws with a false alarm ({100 * rate:.1f} %; stated alpha {100 * ALPHA:.0f} %); "
              f"{located[label]} more with the locate step's channel terms only")
    return 0


if __name__ == "__main__":
    sys.exit(main())
