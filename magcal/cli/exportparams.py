"""``magcal export RESULT.json --ardupilot [N] | --px4 [N]``: a fit as autopilot parameters."""

from __future__ import annotations

import json
import os
import sys

from ..core.errors import InputError
from ..recordings.atomic import write_atomic
from ..recordings.logs import conventions, params
from .common import document, print_json


def _read_result(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a fit result (JSON from 'magcal fit --json'): {exc}") from exc
    if isinstance(d, dict) and "fits" in d:  # magcal.fit/1: one entry per file fitted
        fits = [f for f in d["fits"] if isinstance(f, dict) and "calibration" in f]
        if len(fits) != 1:
            raise InputError(f"{path}: holds {len(fits)} fits with a calibration; export one "
                             "('magcal fit FILE --json > RESULT.json')")
        d = fits[0]
    if isinstance(d, dict) and isinstance(d.get("flight_log"), dict):  # magcal diagnose LOG --json
        d = _from_log_diagnosis(d, path)
    if not isinstance(d, dict) or "calibration" not in d:
        raise InputError(f"{path}: no 'calibration' in it: not the JSON of a successful 'magcal fit'")
    return d


def _from_log_diagnosis(d: dict, path: str) -> dict:
    """The result's calibration (the flight-log fit's) with the log's frame, slot and terms."""
    log = d["flight_log"]
    if d.get("calibration_from") == "flight_log":
        return {**log, "calibration": d["calibration"]}
    if "calibration" in log:  # a result written before the calibration moved to the top
        return log
    raise InputError(f"{path}: its flight-log fit did not succeed ({log.get('failure', 'no calibration')}): "
                     "no calibration in the log's frame to export")


def export_params(args) -> int:
    d = _read_result(args.file)
    if args.ardupilot is not None:
        values, notes, slot = params.ardupilot(d, None if args.ardupilot == -1 else args.ardupilot)
        kind, qgc, default = "ArduPilot", False, f"-ardupilot-{slot}.param"
    else:
        values, notes, slot = params.px4(d, None if args.px4 == -1 else args.px4)
        kind, qgc, default = "PX4", True, f"-px4-{slot}.params"
    out = args.output or (os.path.splitext(args.file)[0] + default)
    source = (d.get("log") or {}).get("file", args.file)
    header = [f"magcal: {kind} parameters from {os.path.basename(str(source))} ({d.get('model', '?')})"] + notes
    write_atomic(out, conventions.format_params(values, header, qgc=qgc).encode("utf-8"))
    for n in notes:
        print(f"magcal: note: {n}", file=sys.stderr)
    if args.json:
        print_json(document("export-params", {"file": args.file, "output": out, "autopilot": kind.lower(),
                                              "slot": slot, "parameters": values, "notes": notes}))
    else:
        print(f"wrote {len(values)} {kind} parameters to {out}")
    return 0
