"""``magcal fit FILE --model sphere|ellipsoid|auto [--json]``: fit a calibration to a recording.

Several FILEs are fitted each and compared in turn (``magcal.fit.compare``: did the hard iron
move between sessions?); the JSON is then ``{"fits": [...each with "file"...], "comparisons":
[...]}``. FILE is a capture, a MotionCal log, or a table: magcal's CSV (``mx,my,mz`` µT, ``t`` s) or
another delimited file read with ``--columns/--unit/--time`` (``magcal.recordings.table``). The JSON object::

    {"model": ..., "calibration": {"offset_ut": [3], "field_ut": r, "soft_iron": [[3×3]]},
     "uncertainty": {"offset_ut": [3], "field_ut": σ, "soft_iron": [[3×3]], "autocorrelation_factor": f},
     "rms_ut": ..., "n_used": ..., "outliers": [indices into FILE's samples],
     "warnings": [sentences, e.g. a field no Earth field could be: a file in another unit], ...}

where a calibrated sample is ``soft_iron @ (m − offset_ut)``. Exit code 0 on a fit, 1 when the
data cannot support any model (the reason is printed), 2 when FILE cannot be read.
"""

from __future__ import annotations

import sys

from .common import add_table_options, field_warning, table_format

HELP = "fit a sphere or ellipsoid calibration to a recording (capture or CSV)"


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", nargs="+",
                   help="a capture, a MotionCal log or a table; several files are fitted each and "
                   "compared in turn (did the hard iron move between sessions?)")
    p.add_argument("--model", choices=("sphere", "ellipsoid", "auto"), default="auto",
                   help="sphere (hard iron), ellipsoid (+ soft iron, falls back when coverage is thin),"
                   " or auto (the best the coverage supports, by BIC); default auto")
    p.add_argument("--no-outliers", action="store_true", help="keep every sample (no Grubbs removal)")
    p.add_argument("--balance", choices=("auto", "directions", "none"), default="auto",
                   help="weight each direction cell equally (auto: for ellipsoids only)")
    p.add_argument("--noise-ut", type=float, default=None,
                   help="noise σ per axis in µT for the Cramér–Rao bound (default: from the residuals)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    add_table_options(p)


def format_text(d: dict) -> str:
    """Human-readable summary of a fit's ``to_dict()`` (pure)."""
    c, u = d["calibration"], d["uncertainty"]
    lines = [f"input       {d['input']}"] if d.get("input") else []
    lines += [
        f"model       {d['model']}",
        "offset_ut   " + " ".join(f"{v:9.3f}" for v in c["offset_ut"])
        + "   ± " + " ".join(f"{v:.3f}" for v in u["offset_ut"])
        + (f"   (widened ×{u['autocorrelation_factor']:.1f}: the residuals are correlated in time)"
           if u.get("autocorrelation_factor", 1.0) >= 1.5 else ""),
        f"field_ut    {c['field_ut']:9.3f}   ± {u['field_ut']:.3f}",
    ]
    for i, row in enumerate(c["soft_iron"]):
        lines.append(("soft_iron   " if i == 0 else "            ") + " ".join(f"{v:9.5f}" for v in row)
                     + "   ± " + " ".join(f"{v:.5f}" for v in u["soft_iron"][i]))
    lines += [
        "crlb_ut     " + " ".join(f"{v:9.3f}" for v in d["crlb_offset_ut"]) + "   (Cramér–Rao bound of the offset)",
        f"rms_ut      {d['rms_ut']:9.3f}",
        f"samples     {d['n_used']} used, {len(d['outliers'])} removed as outliers",
        f"why         {d['reason']}",
    ]
    return "\n".join(lines)


def _fit_file(path: str, args) -> tuple[dict, int]:
    """(the fit as a dict, exit code 0/1) for one file; InputError when it cannot be read."""
    from ..app.load import load_series
    from ..core.errors import InputError
    from ..fit import fit

    series = load_series(path, table_format(args))
    if len(series) == 0:
        raise InputError(f"{path}: no samples")
    result = fit(
        series, model=args.model, outliers=not args.no_outliers, noise_ut=args.noise_ut, balance=args.balance
    )
    if not result:
        print(f"magcal fit: {path}: {result.reason}: {result.message}", file=sys.stderr)
        return result.to_dict(), 1
    d = result.to_dict()
    d["warnings"] = field_warning(d["calibration"]["field_ut"])
    if series.source:
        d["input"] = series.source
    return d, 0


def format_comparison(a: str, b: str, c: dict) -> str:
    """One line: did the offset move from session ``a`` to ``b`` (pure)?"""
    d = ", ".join(f"{v:+.3f}" for v in c["offset_change_ut"])
    p = "p < 1e-12" if c["p_value"] < 1e-12 else f"p = {c['p_value']:.2g}"
    verdict = (f"more than the two fits' uncertainty allows: the hard iron changed between these sessions, "
               f"and the older calibration is off by about {c['offset_change_norm_ut']:.2f} µT"
               if c["offset_moved"] else "the same hard iron within the reported uncertainty")
    return (f"{b} vs {a}: offset change ({d}) µT, |Δ| {c['offset_change_norm_ut']:.3f} µT, χ²(3) = "
            f"{c['chi2']:.1f}, {p}: {verdict}; field {c['field_change_ut']:+.3f} µT (z = {c['field_change_z']:+.1f})")


def run(args) -> int:
    from ..core.errors import InputError
    from ..fit.compare import compare_fits
    from .common import print_json

    if args.noise_ut is not None and not args.noise_ut > 0:
        raise InputError(f"--noise-ut must be positive, got {args.noise_ut}")
    if len(args.file) == 1:
        d, code = _fit_file(args.file[0], args)
        if args.json:
            print_json(d)
        elif code == 0:
            print(format_text(d))
        return code
    # several sessions: fit each (a file that cannot be read is reported and the rest go on),
    # then compare each good fit with the previous good one
    fits, worst = [], 0
    for path in args.file:
        try:
            d, code = _fit_file(path, args)
        except InputError as exc:
            print(f"magcal fit: {exc}", file=sys.stderr)
            d, code = {"error": str(exc)}, 2
        worst = max(worst, code)
        fits.append({"file": path, **d})
        if not args.json and code == 0:
            print(f"== {path}\n{format_text(d)}\n")
    good = [f for f in fits if "calibration" in f and f.get("model")]
    comparisons = [
        {"from": a["file"], "to": b["file"], **compare_fits(a, b)} for a, b in zip(good, good[1:])
    ]
    if args.json:
        print_json({"fits": fits, "comparisons": comparisons})
    else:
        for c in comparisons:
            print(format_comparison(c["from"], c["to"], c))
    return worst
