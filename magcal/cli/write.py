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
the frame.

Before anything is sent the calibration is judged by every gate ``calibrate`` and ``run`` judge
(``gates:`` in the configuration): field radius and offset from the calibration itself; sample
count, direction coverage, conditioning, residual RMS and offset uncertainty from the evidence
FILE carries (``"evidence"`` in a ``fit``/``diagnose`` result, or the older keys ``rms_ut``,
``n_used``, ``coverage``, ``uncertainty``). What FILE lacks is recomputed from the recording it
names (``"file"`` of a fit, ``"recording"`` of a diagnosis: ``fit.evidence``, on the calibration
being written) — and where that recording can be read, every gate is judged on what it shows
rather than on what FILE says, so a result edited by hand is judged on the data. A gate that fails, or that can be judged neither way (a bare calibration object,
a truncated result, a recording that is gone), refuses the write — exit 3, naming the gate —
unless ``--force`` is given; a forced write says so on stderr and in the JSON
(``"gates": {"forced": true, ...}``).

Exit status: 0 written and verified; 3 refused by a gate (nothing sent); 4 refused,
unacknowledged, read back different or a read-only device; 6 for a FILE that holds no
calibration; 5 for the device or port. ``--json`` prints ``magcal.write/1``.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from ..core.calibration import Calibration
from ..core.errors import InputError
from ..logic import failures
from ..logic.failures import Failure
from ..logic.gates import Evidence, clear_for_write
from .common import document, load_settings, open_from_settings, print_json
from .exits import Exit, exit_for
from .options import add

HELP = "write a calibration from fit/diagnose JSON to a device (verified by read-back)"

DEVICE_CHANNELS = ("temp_c", "current_a")  # what the device can apply (protocol v1 record)


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", help="JSON from fit/diagnose/calibrate/show --json, or - for stdin")
    add(p, "port", "baud", "dialect", "config", "json")
    p.add_argument("--force", action="store_true",
                   help="write even when the calibration fails a gate (the output records that it was forced)")


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
    from ..recordings.jsonfile import MAX_BYTES, parse_json, read_json

    if path != "-":
        return read_json(path)
    try:
        data = sys.stdin.buffer.read(MAX_BYTES + 1)
    except OSError as exc:
        raise InputError(f"standard input: cannot read: {exc.strerror or exc}") from None
    if len(data) > MAX_BYTES:
        raise InputError(f"standard input: more than {MAX_BYTES} bytes is too large for a JSON result")
    return parse_json(data, "standard input")


def _number(obj, key: str, name: str, n: int | None = None):
    """obj[key] as a finite float (or n of them); None when absent; InputError when malformed."""
    if not isinstance(obj, dict) or obj.get(key) is None:
        return None
    try:
        v = np.asarray(obj[key], dtype=np.float64).reshape(-1 if n else ())
        ok = bool(np.all(np.isfinite(v))) and (n is None or v.shape == (n,))
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        want = f"{n} finite numbers" if n else "a finite number"
        raise InputError(f"{name}: {key!r} must be {want}")
    return tuple(v.tolist()) if n else float(v)


def _result_of(obj) -> dict:
    """The result whose calibration is written: of several fits the last that fitted (pure)."""
    top = obj if isinstance(obj, dict) else {}
    if isinstance(top.get("fits"), list):
        fitted = [f for f in top["fits"] if isinstance(f, dict) and isinstance(f.get("calibration"), dict)]
        top = fitted[-1] if fitted else {}
    return top


def _first(*values):
    return next((v for v in values if v is not None), None)


def evidence_from_json(obj, cal: Calibration, name: str = "<json>") -> Evidence:
    """What a fit/diagnose/calibrate result says about its calibration, for the gates (pure).
    A bare calibration object carries only the offset and the field; of several fits, the one
    ``calibration_from_json`` takes (the last that fitted)."""
    top = _result_of(obj)
    ev = top.get("evidence") if isinstance(top.get("evidence"), dict) else {}
    if top.get("calibration_from") == "flight_log" and isinstance(top.get("flight_log"), dict):
        top = top["flight_log"]  # diagnose on a flight log: its calibration is the flight-log fit's,
        ev = top.get("evidence") if isinstance(top.get("evidence"), dict) else {}  # and so is its evidence
    quality = top.get("quality") if isinstance(top.get("quality"), dict) else {}
    final = top.get("final") if isinstance(top.get("final"), dict) else {}
    rms = _first(_number(ev, "rms_ut", name), _number(top, "rms_ut", name), _number(quality, "rms_ut", name),
                 _number(final, "rms_ut", name))
    sigma = _first(_number(ev, "offset_sigma_ut", name, 3), _number(top.get("uncertainty"), "offset_ut", name, 3))
    samples = _first(_number(ev, "n_used", name), _number(top, "n_used", name), _number(quality, "kept", name))
    coverage = _first(_number(ev, "coverage", name), _number(top, "coverage", name), _number(quality, "coverage", name))
    condition = _number(ev, "condition", name)
    return Evidence(offset_ut=tuple(float(v) for v in cal.offset_ut), field_ut=float(cal.field_ut), rms_ut=rms,
                    offset_sigma_ut=sigma, n_used=None if samples is None else int(samples), coverage=coverage,
                    condition=condition)


def recording_named(obj) -> str | None:
    """The recording a result says its calibration was fitted on (pure)."""
    top = _result_of(obj)
    for key in ("recording", "file"):
        if isinstance(top.get(key), str) and top[key] and top[key] != "-":
            return top[key]
    return None


GATE_EVIDENCE = ("n_used", "coverage", "condition", "rms_ut", "offset_sigma_ut")


def complete_evidence(ev: Evidence, obj, cal: Calibration, notes: list[str]) -> Evidence:
    """The evidence the gates judge. Where the result names a recording that can be read, all of
    it recomputed there for the calibration being written (``fit.evidence``): a result edited by
    hand — its calibration or its evidence — is judged on the data, not on what it says. Else
    what the result carries, the rest left unjudged (and why, in ``notes``)."""
    from dataclasses import replace

    path = recording_named(obj)
    missing = [k for k in GATE_EVIDENCE if getattr(ev, k) is None]
    if path is None:
        return ev
    from ..app.load import load_series
    from ..fit.evidence import evidence
    from .fit import MAX_FIT_SAMPLES

    try:
        if not os.path.isfile(path):  # a device, a pipe or nothing: never read for evidence
            raise InputError("not a regular file")
        series, _ = load_series(path, None, None).only_valid().thinned(MAX_FIT_SAMPLES)
    except (InputError, OSError) as exc:
        if missing:
            notes.append(f"the evidence it lacks ({', '.join(missing)}) could not be recomputed from {path}: {exc}")
        return ev
    fresh = evidence(series.field_ut, cal, series.channels)
    found = {k: (tuple(fresh[k]) if k == "offset_sigma_ut" and fresh[k] else fresh[k]) for k in GATE_EVIDENCE}
    notes.append(f"the gates judged the evidence recomputed from {path} ({fresh['n_used']} samples)")
    return replace(ev, **{k: v for k, v in found.items() if v is not None})


def _left(r) -> str:
    """What the device was left holding after a write that failed (pure)."""
    if r.restored and r.previous is not None and r.previous.calibration is not None:
        return "; the previous calibration was put back"
    if r.discarded:
        return "; the record that failed was discarded: the device holds no calibration"
    if r.restored is False:
        return "; the previous calibration could NOT be put back and the record that failed was not discarded"
    return ""


def _refused(args, clearance) -> int:
    failure = Failure.of_gate(clearance.blocking[0].name)
    if args.json:
        print_json(document("write", {"written": False, "verified": False, **failure.to_dict(),
                                      "message": clearance.summary(), "gates": clearance.to_dict()}))
    else:
        for r in clearance.results:
            print(f"gate       {({True: 'pass', False: 'FAIL'}).get(r.passed, 'NOT JUDGED')}  {r.message}")
        print(f"not written: {clearance.summary()}; nothing was sent (--force writes it anyway)")
    return exit_for(failure)


def run(args) -> int:
    from ..app.procedure import write_verified
    from .ports import with_port

    obj = _read(args.file)
    cal, notes = calibration_from_json(obj, args.file)
    settings = load_settings(args)
    ev = complete_evidence(evidence_from_json(obj, cal, args.file), obj, cal, notes)
    clearance = clear_for_write(settings.gates, ev, force=args.force)
    if not clearance.allowed:
        for n in notes:
            print(f"magcal write: note: {n}", file=sys.stderr)
        return _refused(args, clearance)
    if clearance.forced and clearance.blocking:
        print(f"magcal write: --force: {clearance.summary()}", file=sys.stderr)
    settings = with_port(settings)
    device = open_from_settings(settings)
    with device:
        identity = device.open()
        if not device.abilities.store:
            print(f"magcal write: {settings.port}: a read-only source cannot store a calibration", file=sys.stderr)
            return Exit.WRITE
        try:
            r = write_verified(device, cal, clearance)
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
        "discarded_unverified": r.discarded,
        "previous_record": None if r.previous is None else r.previous.to_dict(),
        **failures.fields(r.failure),
        "message": r.message,
        "notes": notes,
        "gates": clearance.to_dict(),
    })
    if args.json:
        print_json(out)
    else:
        for n in notes:
            print(f"note       {n}")
        print(f"gates      {clearance.summary()}")
        o = r.sent.offset_ut
        print(f"offset     [{o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}] µT   field {r.sent.field_ut:.3f} µT")
        for name, coef in r.sent.coef_ut_per_unit.items():
            print(f"coef       {name} [{', '.join(f'{v:.4f}' for v in coef)}] µT per unit")
        if r.verified:
            print(f"written    yes, and VERIFIED by read-back ({settings.port})")
        else:
            print(f"not written: {r.message}{_left(r)}")
    return Exit.OK if r.verified else exit_for(r.failure)
