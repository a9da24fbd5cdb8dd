"""``magcal fit FILE… --model sphere|ellipsoid|auto [--json]``: fit a calibration to recordings.

FILE is a capture, a MotionCal log, or a table: magcal's CSV (``mx,my,mz`` µT, ``t`` s) or
another delimited file read with ``--columns/--unit/--time`` (``magcal.recordings.table``).
Several FILEs are fitted each and compared in turn (``magcal.fit.compare``: did the hard iron
move between sessions?). The JSON (``magcal.fit/1``) has the same shape for one file or many::

    {"schema": "magcal.fit/1",
     "fits": [{"file": ..., "model": ..., "calibration": {"offset_ut": [3], "field_ut": r, "soft_iron": [[3×3]]},
               "uncertainty": {"offset_ut": [3], "field_ut": σ, "soft_iron": [[3×3]], "autocorrelation_factor": f},
               "rms_ut": ..., "n_samples": ..., "n_used": ..., "outliers": [indices into FILE's samples],
               "warnings": [sentences, e.g. a field no Earth field could be: a file in another unit], ...}, ...],
     "comparisons": [{"from": FILE, "to": FILE, "offset_change_ut": [3], "p_value": ..., ...}, ...]}

where a calibrated sample is ``soft_iron @ (m − offset_ut)``; a file that could not be read
has ``error`` instead. ``magcal write`` takes this JSON and writes the last fit's calibration.
Exit status: 0 on a fit of every file, 3 when the data cannot support any model (the reason is
printed), 6 when a FILE cannot be read.

A recording of more than 250 000 samples (40 min at 100 Hz) is fitted on every k-th sample,
spread over all of it, so that memory stays bounded whatever the file's length; ``reading`` says
so (``thinned_every``, ``samples_read``) and the uncertainty is that of the samples used. Each
fit also has ``reading``: what reading the file met (framing defects, lines left out, damage).
"""

from __future__ import annotations

import sys

from .common import field_warning, reading_report
from .exits import Exit
from .options import add, add_table_options, table_format

HELP = "fit a sphere or ellipsoid calibration to recordings (captures, logs, tables), or a flight log's magnetometer against the expected field"


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", nargs="+",
                   help="a capture, a MotionCal log or a table; several files are fitted each and "
                   "compared in turn (did the hard iron move between sessions?)")
    add(p, "model", default="auto")
    p.add_argument("--no-outliers", action="store_true", help="keep every sample (no Grubbs removal)")
    p.add_argument("--balance", choices=("auto", "directions", "none"), default="auto",
                   help="weight each direction cell equally (auto: for ellipsoids only)")
    add(p, "noise_ut", help="white-noise σ per axis, µT, for the Cramér–Rao bound (default: from the residuals)")
    add(p, "json", "quiet")
    add_table_options(p)
    add(p, "mag")
    p.add_argument("--term", default="auto",
                   help="flight logs: the interference term to judge — auto (current_a, else throttle), "
                   "none, or a channel name (default auto)")


def format_text(d: dict) -> str:
    """Human-readable summary of a fit's ``to_dict()`` (pure)."""
    from .common import calibration_lines

    lines = [f"input       {d['input']}"] if d.get("input") else []
    lines.append(f"model       {d['model']}")
    lines += calibration_lines(d["calibration"], d["uncertainty"])
    n_out = len(d["outliers"])
    lines += [
        "crlb_ut     " + " ".join(f"{v:9.3f}" for v in d["crlb_offset_ut"]) + "   (Cramér–Rao bound of the offset)",
        f"rms_ut      {d['rms_ut']:9.3f}",
        f"samples     {d.get('n_samples', d['n_used'] + n_out)} read, {d['n_used']} fitted"
        + (f" ({n_out} set aside as outliers by Grubbs' test)" if n_out else " (no outliers)"),
        *_thinned_line(d.get("reading") or {}),
        *([f"coverage    {100 * d['coverage']:.0f} % of directions (the share of the sphere's 128 equal cells "
           "the field was seen in)"] if d.get("coverage") is not None else []),
        f"why         {d['reason']}",
    ]
    return "\n".join(lines)


def _thinned_line(reading: dict) -> list[str]:
    from .common import ordinal

    k = reading.get("thinned_every")
    return [f"thinned     every {ordinal(k)} sample of {reading['samples_read']} (a recording over "
            f"{MAX_FIT_SAMPLES:,} samples); the ± are those of the samples fitted".replace(",", " ")] if k else []


MAX_FIT_SAMPLES = 250_000  # a longer recording is fitted on every k-th sample (memory stays bounded)


def _fit_file(path: str, args, ticker) -> tuple[dict, int]:
    """(the fit as a dict, exit status OK or GATE) for one file; InputError when it cannot be read."""
    from ..app.load import load_series
    from ..core.errors import InputError
    from ..fit import fit_calibration
    from .fitlog import fit_log_file, is_flight_log

    if is_flight_log(path):
        return fit_log_file(path, args)
    ticker.doing(f"reading {path}")
    series = load_series(path, table_format(args), args.mag)
    if len(series) == 0:
        raise InputError(f"{path}: no samples")
    n_read = len(series)
    series, every = series.thinned(MAX_FIT_SAMPLES)
    reading = reading_report(series, path)
    ticker.doing(f"fitting {len(series):,} samples of {path}".replace(",", " "))
    result = fit_calibration(
        series, model=args.model, outliers=not args.no_outliers, noise_ut=args.noise_ut, balance=args.balance
    )
    if not result:
        print(f"magcal fit: {path}: {result.reason}: {result.message}", file=sys.stderr)
        return result.to_dict(), Exit.GATE
    d = result.to_dict()
    d["evidence"] = fit_evidence(series, result)
    d["coverage"] = d["evidence"]["coverage"]
    d["n_samples"] = n_read
    d["outliers"] = [int(i) * every for i in d["outliers"]]  # indices into FILE's samples
    d["warnings"] = field_warning(d["calibration"]["field_ut"])
    if series.source:
        d["input"] = series.source
    d["reading"] = reading
    return d, Exit.OK


def fit_evidence(series, result) -> dict:
    """What the write gates judge, on the samples the fit used (``fit.evidence``)."""
    from ..fit.evidence import evidence

    used = result.used if len(result.used) else slice(None)
    return evidence(series.field_ut[used], result.calibration)


def format_comparison(a: str, b: str, c: dict) -> str:
    """One line: did the offset move from session ``a`` to ``b`` (pure)?"""
    d = ", ".join(f"{v:+.3f}" for v in c["offset_change_ut"])
    p = "p < 1e-12" if c["p_value"] < 1e-12 else f"p = {c['p_value']:.2g}"
    verdict = (f"more than the two fits' uncertainty allows: the hard iron changed between these sessions, "
               f"and the older calibration is off by about {c['offset_change_norm_ut']:.2f} µT"
               if c["offset_moved"] else "the same hard iron within the reported uncertainty")
    return (f"{b} vs {a}: offset change ({d}) µT, |Δ| {c['offset_change_norm_ut']:.3f} µT, χ²(3) = "
            f"{c['chi2']:.1f}, {p}: {verdict}; field {c['field_change_ut']:+.3f} µT (z = {c['field_change_z']:+.1f})")


def _fit_each(paths, args) -> tuple[list[dict], int]:
    """Fit each file (one that cannot be read is named and the rest go on): the fits, the worst
    exit status."""
    from ..core.errors import InputError
    from .common import Progress

    fits, worst = [], Exit.OK
    with Progress(quiet=args.quiet).working("fit") as ticker:
        for i, path in enumerate(paths):
            try:
                d, code = _fit_file(path, args, ticker)
            except InputError as exc:
                if len(paths) == 1:
                    raise
                print(f"magcal fit: {exc}", file=sys.stderr)
                d, code = {"error": str(exc)}, Exit.INPUT
            worst = max(worst, code)
            fits.append({"file": path, **d})
            if len(paths) > 1 and i + 1 < len(paths):
                ticker.step(i + 1, len(paths), f"session {paths[i + 1]}")
    return fits, worst


def run(args) -> int:
    from ..fit.compare import compare_fits
    from .common import document, print_json

    fits, worst = _fit_each(args.file, args)
    good = [f for f in fits if "calibration" in f and f.get("model") and "log" not in f]
    comparisons = [
        {"from": a["file"], "to": b["file"], **compare_fits(a, b)} for a, b in zip(good, good[1:])
    ]
    if args.json:
        print_json(document("fit", {"fits": fits, "comparisons": comparisons}))
        return worst
    from .fitlog import format_log_text

    for f in (f for f in fits if "calibration" in f and f.get("model")):
        text = format_log_text(f) if "log" in f else format_text(f)
        print(f"== {f['file']}\n{text}\n" if len(fits) > 1 else text)
    for c in comparisons:
        print(format_comparison(c["from"], c["to"], c))
    return worst
