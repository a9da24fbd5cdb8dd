"""A fit result (the JSON of ``magcal fit``) as an autopilot's parameters.

Only what the autopilot can apply is written: offsets, the symmetric soft iron, and one
interference term (current or throttle). A motors-running step (``motors_on``) is folded into
the offsets, so the parameters are right while the motors run — in flight, where heading
matters — and off by that step on the ground with the motors stopped; other channel terms
(temperature …) cannot be expressed and are named in the notes.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ...core.calibration import Calibration
from ...core.errors import InputError
from . import conventions as cv

EXPORTABLE = ("current_a", "throttle")
AP_OFFSET_LIMIT_MG = 1250.0  # ArduPilot's default COMPASS_OFFS_MAX in current firmware


def for_autopilot(d: Mapping) -> tuple[Calibration, str | None, list[str]]:
    """(the calibration an autopilot can carry, its interference term, notes on what changed)."""
    if "calibration" not in d:
        raise InputError("the result holds no calibration (a failed fit?)")
    cal = Calibration.from_dict(d["calibration"])
    coefs = dict(cal.coef_ut_per_unit)
    notes, offset = [], cal.offset_ut.copy()
    if "motors_on" in coefs:
        step = coefs.pop("motors_on")
        offset = offset + step
        notes.append("the motors-running step (" + ", ".join(f"{v:+.2f}" for v in step)
                     + " µT) is folded into the offsets: right with the motors running, off by that on the ground")
    terms = [k for k in coefs if k in EXPORTABLE]
    dropped = [k for k in coefs if k not in EXPORTABLE]
    if dropped:
        notes.append(f"terms the autopilot cannot apply are left out: {', '.join(dropped)}")
    if len(terms) > 1:
        notes.append(f"only one interference term fits the autopilot; {terms[1]} is left out")
    term = terms[0] if terms else None
    kept = {term: coefs[term]} if term else {}
    return Calibration(offset_ut=offset, field_ut=cal.field_ut, soft_iron=cal.soft_iron, coef_ut_per_unit=kept,
                       reference={k: 0.0 for k in kept}), term, notes


def _frame_notes(d: Mapping, autopilot: str) -> list[str]:
    log = d.get("log")
    if log is None:
        return ["the result is not from a flight log: its frame is taken as the body frame the autopilot "
                "applies its parameters in"]
    if log.get("autopilot") != autopilot:
        return [f"the result is from a {log.get('autopilot')} log: the frames of the two autopilots may differ"]
    return []


def ardupilot(d: Mapping, compass: int | None) -> tuple[dict[str, float], list[str], int]:
    """(COMPASS_* parameters, notes, compass number 1…) for ``compass`` (default: the log's)."""
    log = d.get("log") or {}
    if compass is None:
        slot = log.get("slot") if log.get("autopilot") == "ardupilot" else None
        compass = 1 if slot is None else slot + 1
    if compass < 1:
        raise InputError(f"--ardupilot {compass}: ArduPilot numbers its compasses from 1")
    cal, term, notes = for_autopilot(d)
    notes = notes + _frame_notes(d, "ardupilot")
    if term == "throttle":
        notes.append("throttle compensation (COMPASS_MOTCT 1) expects throttle 0…1")
    numbered = bool(log.get("ardupilot_numbered_names")) and log.get("autopilot") == "ardupilot"
    params = cv.to_ardupilot(cal, compass - 1, term, numbered)
    ofs = [params[f"COMPASS{compass}_OFS_{a}" if numbered else f"COMPASS_OFS{cv.ap_suffix(compass - 1)}_{a}"]
           for a in "XYZ"]
    big = [a for a, v in zip("XYZ", ofs) if abs(v) > AP_OFFSET_LIMIT_MG]
    if big:
        notes.append(f"offsets beyond {AP_OFFSET_LIMIT_MG:.0f} mG on {''.join(big)}: ArduPilot's pre-arm check "
                     "(COMPASS_OFFS_MAX) may refuse them")
    return params, notes, compass


def px4(d: Mapping, n: int | None) -> tuple[dict[str, float], list[str], int]:
    """(CAL_MAGn_* parameters, notes, n) for calibration slot ``n`` (default: the log's)."""
    log = d.get("log") or {}
    if n is None:
        n = log.get("slot") if log.get("autopilot") == "px4" else None
        if n is None:
            raise InputError("which CAL_MAGn? the result does not say; give --px4 N")
    if n < 0:
        raise InputError(f"--px4 {n}: PX4 numbers its calibrations from 0 (CAL_MAG0)")
    cal, term, notes = for_autopilot(d)
    notes = notes + _frame_notes(d, "px4")
    rot = np.asarray(log.get("sensor_to_body", np.eye(3)), np.float64) if log.get("autopilot") == "px4" else np.eye(3)
    values = cv.to_px4(cal, n, rot, term)
    if any(values[f"CAL_MAG{n}_{a}ODIAG"] for a in "XYZ") or term:
        notes.append("CAL_MAGn_xODIAG and xCOMP exist only in PX4 releases since 2020 (v1.11 on); older firmware "
                     "ignores them and applies offsets and scales alone")
    return values, notes, n
