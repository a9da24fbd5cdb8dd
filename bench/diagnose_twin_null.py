"""``diagnose``'s false alarms on twins of real recordings, beside the white-noise simulator.

    python3 bench/diagnose_twin_null.py [--draws N] [--first-seed S] [--max-samples M] [--only NAME,NAME]
                                           [--without-f-alone]

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
false alarm in each of the three, then the overall rates against alpha. A new ``--first-seed``
gives draws never seen.
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
    (``twin_null``: diagnose's own; False: its tests referred to the F distribution alone)."""
    rng = np.random.default_rng([seed, 0x7E1])
    m, valid = model.simulate(u, t, None, seed)
    chans = channels_for(t, rng, seed, "current_a" if rng.uniform() < 0.5 else "temp_c")
    s = Series(t_s=t[valid], field_ut=m[valid], channels={c: v[valid] for c, v in chans.items()})
    return [f.effect for f in diagnose(s, twin_null=twin_null).findings if f.effect in EFFECT.values()]


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
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    seed0 = args.first_seed if args.first_seed is not None else int.from_bytes(os.urandom(4), "little")
    print(f"diagnose on twins of real recordings: {args.draws} draws each, first seed {seed0}, alpha {ALPHA} "
          "(family-wise, per recording)")
    print(f"{'recording':<44}{'n':>6}{'wander µT (parts)':>28}{'twin FA':>10}{'F alone':>10}{'white FA':>10}{'CPU s':>7}")
    totals = {"twin": [0, 0], "F alone": [0, 0], "white": [0, 0]}
    for k, name, model, u, t in recordings(args.only, args.max_samples):
        c0 = time.process_time()
        line = {}
        for label, mdl, own in (("twin", model, True), ("F alone", model, False), ("white", white_twin(model), True)):
            if label == "F alone" and args.without_f_alone:
                line[label] = "-"
                continue
            hits = [bool(false_alarms(mdl, u, t, seed0 + 1000 * k + j, own)) for j in range(args.draws)]
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
        print(f"all {label:>7}: {fa}/{n} draws with a false alarm ({100 * rate:.1f} %; stated alpha {100 * ALPHA:.0f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
