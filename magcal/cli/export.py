"""``magcal export FILE [-o OUT] [--json]``: a recording (capture, CSV, MotionCal log, a flight
log's magnetometer with ``--mag N``) as CSV ``t,mx,my,mz,temp_c`` (s, µT, °C) plus its other
channels, and ``valid`` when some samples are flagged; what reading assumed stays assumed (no
``t`` for a table timed by its sample index, ``mag_x,mag_y,mag_z`` for a unit that was guessed). Floats are written in shortest round-trip
form: reading the CSV back gives the same numbers bit for bit. OUT defaults to FILE with a
``.csv`` suffix. CSV is the default format (``--csv`` may be given). ``--json`` prints
``magcal.export/1``.

``magcal export RESULT.json --ardupilot [N] | --px4 [N]``: a fit (the JSON of ``magcal fit``) as
the autopilot's parameters — ArduPilot compass N (1 → COMPASS_OFS_*, 2 → COMPASS_OFS2_* …):
COMPASS_OFS/DIA/ODI/SCALE and, for a kept current or throttle term, COMPASS_MOT and MOTCT, in
MAVProxy/Mission Planner's ``NAME VALUE`` form; PX4 CAL_MAGN_* (N from 0): OFF, SCALE, ODIAG,
COMP and CAL_MAG_COMP_TYP, in QGroundControl's tab-separated form. N defaults to the slot of the
log the fit came from; ``--json`` prints ``magcal.export-params/1``. The formulas:
``magcal.recordings.logs.conventions`` and docs/flightlogs.md."""

from __future__ import annotations

import os

from ..app.load import load_series
from ..core.errors import InputError
from ..recordings.table import save_csv
from .common import document, print_json, reading_report
from .options import add, add_table_options, table_format

HELP = "export a recording as CSV (t, mx, my, mz in µT, channels), or a fit as ArduPilot/PX4 parameters"


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", help="a recording (for CSV), or the JSON of magcal fit or of magcal "
                   "diagnose on a flight log (for --ardupilot/--px4)")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--csv", action="store_true", help="write the recording as CSV (the default)")
    what.add_argument("--ardupilot", nargs="?", type=int, const=-1, metavar="N",
                      help="write ArduPilot parameters for compass N (1, 2, 3 …; default: the log's)")
    what.add_argument("--px4", nargs="?", type=int, const=-1, metavar="N",
                      help="write PX4 CAL_MAGN_* parameters (N from 0; default: the log's)")
    add(p, "output", help="the file to write (default: FILE.csv, FILE-ardupilot-N.param, FILE-px4-N.params)")
    add(p, "json", "quiet")
    add_table_options(p)
    add(p, "mag")


def run(args) -> int:
    if args.ardupilot is not None or args.px4 is not None:
        from .exportparams import export_params

        return export_params(args)
    return _export_csv(args)


def _export_csv(args) -> int:
    out = args.output or (os.path.splitext(args.file)[0] + ".csv")
    if os.path.exists(out) and os.path.exists(args.file) and os.path.samefile(out, args.file):
        raise InputError(f"{out}: refusing to overwrite the input; give -o OUT")
    from .common import Progress

    with Progress(quiet=args.quiet).working(f"export {args.file}") as ticker:
        ticker.doing("reading")
        series = load_series(args.file, table_format(args), args.mag)
        if len(series) == 0:  # as fit says of it: an empty CSV would look like an export that worked
            raise InputError(f"{args.file}: no samples to export; nothing written")
        reading = reading_report(series, args.file)
        ticker.doing(f"writing {len(series):,} samples to {out}".replace(",", " "))
        columns = save_csv(series, out)
    summary = document("export", {
        "file": args.file,
        "output": out,
        "n_samples": len(series),
        "n_invalid": int((~series.valid).sum()),
        "columns": columns,
        "reading": reading,
    })
    if args.json:
        print_json(summary)
    else:
        print(f"wrote {len(series)} samples to {out} ({','.join(summary['columns'])})")
    return 0
