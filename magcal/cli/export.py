"""``magcal export FILE [-o OUT] [--json]``: a recording (capture, CSV, MotionCal log) as CSV
``t,mx,my,mz,temp_c`` (s, µT, °C) plus its other channels, and ``valid`` when some samples are
flagged. Floats are written in shortest round-trip form: reading the CSV back gives the same
numbers bit for bit. OUT defaults to FILE with a ``.csv`` suffix. CSV is the format (``--csv``
may be given, and changes nothing). ``--json`` prints ``magcal.export/1``."""

from __future__ import annotations

import os

from ..app.load import load_series
from ..core.errors import InputError
from ..recordings.table import save_csv
from .common import document, print_json, reading_report
from .options import add, add_table_options, table_format

HELP = "export a recording as CSV (t, mx, my, mz in µT, temp_c, other channels)"


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", help="a capture, a CSV or a MotionCal log")
    p.add_argument("--csv", action="store_true", help="write CSV (the one export format, so the default)")
    add(p, "output", help="the CSV file to write (default: FILE with a .csv suffix)")
    add(p, "json", "quiet")
    add_table_options(p)


def run(args) -> int:
    out = args.output or (os.path.splitext(args.file)[0] + ".csv")
    if os.path.exists(out) and os.path.samefile(out, args.file):
        raise InputError(f"{out}: refusing to overwrite the input; give -o OUT")
    from .common import Progress

    with Progress(quiet=args.quiet).working(f"export {args.file}") as ticker:
        ticker.doing("reading")
        series = load_series(args.file, table_format(args))
        reading = reading_report(series, args.file)
        ticker.doing(f"writing {len(series):,} samples to {out}".replace(",", " "))
        save_csv(series, out)
    summary = document("export", {
        "file": args.file,
        "output": out,
        "n_samples": len(series),
        "n_invalid": int((~series.valid).sum()),
        "columns": ["t", "mx", "my", "mz"] + (["temp_c"] if "temp_c" in series.channels else [])
        + sorted(k for k in series.channels if k != "temp_c") + ([] if series.valid.all() else ["valid"]),
        "reading": reading,
    })
    if args.json:
        print_json(summary)
    else:
        print(f"wrote {len(series)} samples to {out} ({','.join(summary['columns'])})")
    return 0
