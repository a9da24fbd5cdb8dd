"""``magcal fit FILE --model sphere|ellipsoid|auto [--json]``: fit a calibration to a recording.

FILE is a capture, a MotionCal log, or a table: magcal's CSV (``mx,my,mz`` µT, ``t`` s) or
another delimited file read with ``--columns/--unit/--time`` (``magcal.table``). The JSON object::

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
    p.add_argument("file", metavar="FILE", help="a capture or a CSV with mx,my,mz (µT) columns")
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


def run(args) -> int:
    from ..capture import load_series
    from ..errors import InputError
    from ..fit import fit

    if args.noise_ut is not None and not args.noise_ut > 0:
        raise InputError(f"--noise-ut must be positive, got {args.noise_ut}")
    series = load_series(args.file, table_format(args))
    if len(series) == 0:
        raise InputError(f"{args.file}: no samples")
    result = fit(
        series, model=args.model, outliers=not args.no_outliers, noise_ut=args.noise_ut, balance=args.balance
    )
    if not result:
        if args.json:
            from .common import print_json

            print_json(result.to_dict())
        print(f"magcal fit: {result.reason}: {result.message}", file=sys.stderr)
        return 1
    d = result.to_dict()
    d["warnings"] = field_warning(d["calibration"]["field_ut"])
    if series.source:
        d["input"] = series.source
    if args.json:
        from .common import print_json

        print_json(d)
    else:
        print(format_text(d))
    return 0
