"""``magcal write FILE --port URL [--json]``: put a calibration computed offline on a device and
prove it arrived — write, compare the echo, read back, compare again; on a mismatch the
calibration the device held before is put back.

FILE (``-`` for standard input) is what ``fit --json``, ``diagnose --json``, ``calibrate --json``
or ``show --json`` print — anything with a ``"calibration"`` object — or that object alone::

    {"offset_ut": [3], "field_ut": r, "soft_iron": [[3×3]],
     "coef_ut_per_unit": {"temp_c": [3], "current_a": [3]}, "reference": {"temp_c": T0}}

Only what a device can apply is written, and what is left out is named: a drift in time
(``t_s``) belonged to the recording it was found in, and other covariates have no input on the
device. A non-symmetric matrix (another tool's convention) is written as its symmetric polar
factor √(AᵀA), which gives every field the same magnitude; the rotation it leaves out only turns
the frame. Exit status: 0 written and verified; 4 refused, unacknowledged, read back different or a
read-only device; 6 for a FILE that holds no calibration; 5 for the device or port.
``--json`` prints ``magcal.write/1``.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from ..core.calibration import Calibration
from ..core.errors import InputError
from .common import device_settings, document, open_from_settings, print_json
from .exits import Exit
from .options import add

HELP = "write a calibration from fit/diagnose JSON to a device (verified by read-back)"

DEVICE_CHANNELS = ("temp_c", "current_a")  # what the device can apply (protocol v1 record)


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", help="JSON from fit/diagnose/calibrate/show --json, or - for stdin")
    add(p, "port", "baud", "dialect", "config", "json")


def calibration_from_json(obj, name: str = "<json>") -> tuple[Calibration, list[str]]:
    """(the calibration to write, notes on what was changed or left out), or InputError (pure).
    From ``fit --json`` of several sessions, the last one that fitted (the newest) is taken."""
    notes = []
    if isinstance(obj, dict) and isinstance(obj.get("fits"), list):
        fitted = [f for f in obj["fits"] if isinstance(f, dict) and isinstance(f.get("calibration"), dict)]
        if not fitted:
            raise InputError(f"{name}: none of its fits produced a calibration")
        if len(fitted) > 1:
            notes.append(f"took the last of {len(fitted)} fits: {fitted[-1].get('file', '?')}")
        obj = fitted[-1]
    if isinstance(obj, dict) and isinstance(obj.get("calibration"), dict):
        obj = obj["calibration"]
    elif isinstance(obj, dict) and "calibration" in obj:
        raise InputError(f"{name}: its \"calibration\" is empty (the fit or run it came from did not produce one)")
    if not isinstance(obj, dict):
        raise InputError(f"{name}: not a calibration (a JSON object with offset_ut, field_ut, soft_iron)")
    missing = [k for k in ("offset_ut", "field_ut") if k not in obj]
    if missing:
        raise InputError(f"{name}: the calibration lacks {', '.join(missing)}")
    try:
        offset = np.asarray(obj["offset_ut"], dtype=np.float64).reshape(3)
        field = float(obj["field_ut"])
        w = np.asarray(obj.get("soft_iron", np.eye(3)), dtype=np.float64).reshape(3, 3)
        coefs = {k: np.asarray(v, dtype=np.float64).reshape(3) for k, v in dict(obj.get("coef_ut_per_unit") or {}).items()}
        reference = {k: float(v) for k, v in dict(obj.get("reference") or {}).items()}
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: malformed calibration ({exc}): offset_ut needs 3 numbers, soft_iron 3×3") from None
    if not (np.isfinite(field) and field > 0):
        raise InputError(f"{name}: field_ut must be a positive number, got {obj['field_ut']!r}")
    if not np.all(np.isfinite(w)):
        raise InputError(f"{name}: soft_iron holds a non-finite number")
    if np.max(np.abs(w - w.T)) > 1e-9 * max(1.0, np.max(np.abs(w))):
        if np.linalg.det(w) <= 0:
            raise InputError(f"{name}: soft_iron has a non-positive determinant: it mirrors the field")
        _, sv, vt = np.linalg.svd(w)
        w = vt.T @ np.diag(sv) @ vt  # √(WᵀW): same |W m| for every m
        notes.append("soft_iron was not symmetric: wrote its symmetric polar factor √(AᵀA) (same field "
                     "magnitudes; the rotation left out only turns the frame)")
    for k in sorted(coefs):
        if k in DEVICE_CHANNELS:
            continue
        what = ("a drift in time belongs to the recording it was found in" if k == "t_s"
                else "the device has no such input")
        notes.append(f"left out the {k} term ({what})")
        del coefs[k]
        reference.pop(k, None)
    if coefs.get("current_a") is not None and reference.get("current_a", 0.0) != 0.0:
        ref = reference.pop("current_a")
        offset = offset + coefs["current_a"] * (0.0 - ref)  # the same correction, referred to 0 A
        notes.append(f"current term re-referred from {ref:g} A to 0 A (the device's reference)")
    reference = {k: v for k, v in reference.items() if k in coefs}
    try:
        cal = Calibration(offset_ut=offset, field_ut=field, soft_iron=w, coef_ut_per_unit=coefs, reference=reference)
    except ValueError as exc:
        raise InputError(f"{name}: {exc}") from None
    return cal, notes


def _read(path: str):
    try:
        text = sys.stdin.read() if path == "-" else open(path, encoding="utf-8").read()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path} line {exc.lineno}: not JSON ({exc.msg})") from None


def run(args) -> int:
    from ..app.procedure import write_verified

    cal, notes = calibration_from_json(_read(args.file), args.file)
    settings = device_settings(args)
    device = open_from_settings(settings)
    with device:
        identity = device.open()
        if not device.abilities.store:
            print(f"magcal write: {settings.port}: a read-only source cannot store a calibration", file=sys.stderr)
            return Exit.WRITE
        try:
            r = write_verified(device, cal)
        except ValueError as exc:  # the device's record cannot carry it (range, terms)
            raise InputError(f"{settings.port}: this device cannot hold that calibration: {exc}") from None
    lost = sorted(set(cal.coef_ut_per_unit) - set(r.sent.coef_ut_per_unit))
    if lost:  # e.g. the MotionCal packet has room for hard and soft iron only
        notes.append(f"this device cannot hold the {', '.join(lost)} term(s): written without them")
    out = document("write", {
        "device": identity.to_dict(),
        "port": settings.port,
        "sent": r.sent.to_dict(),
        "written": r.written,
        "verified": r.verified,
        "stored": None if r.stored is None else r.stored.to_dict(),
        "restored_previous": r.restored,
        "failure": r.failure,
        "message": r.message,
        "notes": notes,
    })
    if args.json:
        print_json(out)
    else:
        for n in notes:
            print(f"note       {n}")
        o = r.sent.offset_ut
        print(f"offset     [{o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}] µT   field {r.sent.field_ut:.3f} µT")
        for name, coef in r.sent.coef_ut_per_unit.items():
            print(f"coef       {name} [{', '.join(f'{v:.4f}' for v in coef)}] µT per unit")
        if r.verified:
            print(f"written    yes, and VERIFIED by read-back ({settings.port})")
        else:
            back = {True: "; the previous calibration was put back", False: "; the previous one could NOT be put back"}
            print(f"not written: {r.message}{back.get(r.restored, '')}")
    return Exit.OK if r.verified else Exit.WRITE
