"""``magcal track FILE [--jsonl | --json]``: replay a recording through the tracker.

The tracker (``magcal.fit.tracker``) keeps the calibration in force as samples arrive: a full
ellipsoid from a coverage-balanced memory, older samples counting less at the wander rate the
data show. ``track`` feeds FILE's samples in order and reports each change of the calibration in
force. A change at ``sample`` k holds for the samples after k (0-based, FILE's data rows)::

    {"sample": k, "t": s, "model": "ellipsoid", "offset_ut": [3], "soft_iron": [[3×3]],
     "field_ut": r, "offset_sigma_ut": [3], "wander_ut2_per_s": q, "noise_ut": s,
     "buffered": n, "coverage": c}

(a calibrated sample is ``soft_iron @ (m − offset_ut)``). When the samples in memory stop
determining a calibration the change says so: ``offset_ut``, ``soft_iron``, ``field_ut`` and
``model`` null and a ``reason``. The last change is the calibration as it is reported
(``fit.tracker_check``): where fit's gates, on the samples in memory or on the whole of FILE,
refuse the tracker's model it falls back to the fullest model they accept (``refused_model``
names the one refused), and every σ — ``offset_sigma_ut``, ``field_sigma_ut``,
``soft_iron_sigma`` — is at least ``fit``'s on the same samples. ``--jsonl`` prints one such
object per line as they happen; ``--json`` one object ``{"format": "magcal.track", "version": 1, "samples", "skipped", "changes":
[...], "final": {...} | null, "input"}``; without either, a summary. ``--rate HZ`` times the rows
at HZ (for a file without a time column, whose rows are otherwise one second apart). A flight
log (PX4 ULog, ArduPilot DataFlash) is replayed as its magnetometer's raw samples, the log's own
calibration undone; ``--mag N`` chooses the magnetometer of a log that holds several.
Exit status (``magcal --help``): 0 when a calibration came into force, 3 when none did (the
samples never pinned one, or gave only a field below the Earth's), 2 for a bad option, 6 when
FILE cannot be read. A final field outside the Earth's 15–100 µT is warned of on stderr, as
``fit`` does (a file in another unit).
"""

from __future__ import annotations

import json
import sys

from .options import add_table_options, table_format
from .options import add
from .exits import Exit

HELP = "replay a recording through the tracker: the calibration in force at every sample"
FORMAT, VERSION = "magcal.track", 1


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", help="a capture, a MotionCal log, a table or a flight log (--mag N)")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--jsonl", action="store_true", help="one JSON object per change, one per line, as they happen")
    out.add_argument("--json", action="store_true", help="one JSON object with every change")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="sample rate: time the rows at HZ instead of the file's time column")
    add_table_options(p)
    add(p, "mag")


def _times(series, rate):
    import numpy as np

    from ..core.errors import ConfigError

    if rate is None:
        return series.t_s
    if not rate > 0:
        raise ConfigError(f"--rate must be positive, got {rate}")
    return np.arange(len(series)) / float(rate)


def _why_none(tracker) -> str:
    """Why no calibration came into force, in words."""
    from ..recordings.table import unit_guess

    low, floor = tracker.low_field_ut, tracker.config.min_field_ut
    if low is None:
        return "the samples never pinned one (too few, or too few directions)"
    guess = unit_guess(low)
    cause = (f"is the file in {guess}? (--unit {guess})" if guess else
             "the board has hardly turned: a sphere of a few µT wraps its cloud of samples")
    return f"the only spheres the samples gave had a field of {low:.3g} µT, below the Earth's {floor:.3g} µT: {cause}"


def _summary(changes: list[dict], n: int, skipped: int, source: str | None, why: str) -> str:
    lines = [f"input       {source}"] if source else []
    good = [c for c in changes if c.get("offset_ut") is not None]
    lines.append(f"samples     {n} ({skipped} not finite, skipped); {len(changes)} changes of the calibration")
    if not good:
        return "\n".join(lines + [f"no calibration came into force: {why}"])
    first, last = good[0], changes[-1]
    lines.append(f"first       after sample {first['sample']} ({first['model']})")
    lines.extend(_listed(good))
    if last.get("offset_ut") is None:
        return "\n".join(lines + [f"last        withdrawn after sample {last['sample']}: {last['reason']}"])
    lines.append(f"final       {last['model']}, wander {last['wander_ut2_per_s']:.3g} µT²/s, noise "
                 f"{last['noise_ut']:.3f} µT, {100 * last['coverage']:.0f} % of directions in memory")
    if last.get("refused_model"):
        lines.append(f"            (the tracker ran {last['refused_model']}, which fit's gates refuse on these samples)")
    lines.append("offset_ut   " + " ".join(f"{v:9.3f}" for v in last["offset_ut"]) + "  ± (1σ) "
                 + " ".join(f"{v:.3f}" for v in last["offset_sigma_ut"]))
    if last.get("field_sigma_ut") is not None:
        lines.append(f"field_ut    {last['field_ut']:9.3f}  ± (1σ) {last['field_sigma_ut']:.3f}")
    for i, row in enumerate(last["soft_iron"]):
        lines.append(("soft_iron   " if i == 0 else "            ") + " ".join(f"{v:9.5f}" for v in row))
    return "\n".join(lines)


def _listed(good: list[dict]) -> list[str]:
    """Up to about nine of the changes, the first and the last among them. The calibration as
    it is reported (``_reported``) is a change of its own at the sample of the tracker's last
    refit; where it only restates that refit (σ at least fit's, the same values) it is listed
    once, marked as such, not as a second row that reads as a repeat."""
    restated = len(good) > 1 and good[-1]["sample"] == good[-2]["sample"]
    shown = good[:-2] + good[-1:] if restated else good
    step = max(1, len(shown) // 8)
    rows = shown[::step] + ([shown[-1]] if (len(shown) - 1) % step else [])
    out = [f"  sample {c['sample']:>8}  t {c['t']:10.2f} s  offset_ut "
           + " ".join(f"{v:9.3f}" for v in c["offset_ut"]) + f"  field_ut {c['field_ut']:8.3f}" for c in rows]
    if restated:
        out[-1] += "  (as reported: σ at least fit's)"
    return out


def run(args) -> int:
    from ..app.load import load_series
    from ..core.errors import InputError
    import numpy as np

    from ..fit.tracker import Tracker
    from .common import field_warning, print_json

    series = load_series(args.file, table_format(args), args.mag)
    if len(series) == 0:
        raise InputError(f"{args.file}: no samples")
    t = _times(series, args.rate)
    m = series.field_ut.copy()
    m[~series.valid] = float("nan")  # a flagged row is offered and skipped, so indices stay rows
    tracker, changes = Tracker(), []
    for row, tt in zip(m.tolist(), t.tolist()):
        ev = tracker.add(row, tt)
        if ev is None:
            continue
        changes.append(ev.to_dict())
        if args.jsonl:
            sys.stdout.write(json.dumps(changes[-1], allow_nan=False) + "\n")
            sys.stdout.flush()
    final = _reported(tracker, m[np.all(np.isfinite(m), axis=1)])
    if final is not None and (not changes or final.to_dict() != changes[-1]):
        changes.append(final.to_dict())
        if args.jsonl:
            sys.stdout.write(json.dumps(changes[-1], allow_nan=False) + "\n")
    code = Exit.OK if any(c.get("offset_ut") is not None for c in changes) else Exit.GATE
    if args.json:
        print_json({"format": FORMAT, "version": VERSION, "input": series.source, "samples": tracker.n,
                    "skipped": tracker.skipped, "changes": changes,
                    "final": changes[-1] if changes and changes[-1].get("offset_ut") is not None else None})
    elif not args.jsonl:
        print(_summary(changes, tracker.n, tracker.skipped, series.source, _why_none(tracker)))
    if code:
        print(f"magcal track: no calibration came into force: {_why_none(tracker)}", file=sys.stderr)
    elif changes[-1].get("field_ut") is not None:
        field_warning(changes[-1]["field_ut"])
    return code


def _reported(tracker, recording):
    """The calibration in force at the end as it is reported (``fit.tracker_check.checked``: a
    model fit's gates accept on the memory and on the whole recording, σ at least fit's there),
    a last change at the sample of the last refit; a withdrawal where fit refuses every model;
    None where the tracker has no calibration."""
    from ..fit.tracker import Withdrawal
    from ..fit.tracker_check import checked

    if tracker.estimate is None:
        return None
    rep = checked(tracker, recording)
    if rep is None:
        return Withdrawal(sample=tracker.estimate.sample, t_s=tracker.estimate.t_s,
                          reason="fit's gates refuse every model on the samples in memory or in the recording")
    return rep
