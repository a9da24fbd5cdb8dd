"""``magcal calibrate``: connect, identify, stream, collect, fit, write back, read back, compare.

Exit codes: 0 after a verified write (or, with ``--no-write``, after a fit that passed every
gate); 3 when a gate was not met in time (the message names it); 4 when the write was refused,
unacknowledged or read back different; 2 for a device, port or input error.
"""

from __future__ import annotations

import time

from ..app.procedure import calibrate
from ..logic.session import Session
from .common import (
    Progress,
    add_config_option,
    add_json_option,
    add_port_options,
    load_settings,
    open_from_settings,
    print_json,
)

HELP = "calibrate a device end to end and write the result back (verified by read-back)"

EXIT_OK, EXIT_GATE, EXIT_WRITE = 0, 3, 4


def add_arguments(p) -> None:
    add_port_options(p)
    add_config_option(p)
    add_json_option(p)
    p.add_argument("--no-write", action="store_true", help="fit and report, but do not write to the device")
    p.add_argument("--timeout", type=float, metavar="S", help="give up after S seconds (default 120)")
    p.add_argument("--rate", type=int, metavar="HZ", help="measurement rate, 1…100 Hz (default 50)")
    p.add_argument("--model", choices=("sphere", "ellipsoid", "auto"), help="fit model (default auto)")
    p.add_argument("--record", metavar="FILE", help="also keep the raw bytes as a capture")


def _describe(session: Session) -> str:
    p = session.progress()
    est = ""
    if p["offset_ut"]:
        o = p["offset_ut"]
        est = f"  offset [{o[0]:7.2f} {o[1]:7.2f} {o[2]:7.2f}] µT  |B| {p['field_ut']:5.1f} µT"
    failing = [g.name for g in session.failing_gates()] if p["status"] == "collecting" else []
    waiting = f"  waiting on: {', '.join(failing)}" if failing else ""
    return f"{p['status']:<10} {p['samples']:6d} samples  {100 * p['coverage']:3.0f}% covered{est}{waiting}"


def run(args) -> int:
    settings = load_settings(args, timeout_s=args.timeout, rate_hz=args.rate, model=args.model)
    progress = Progress(quiet=False)
    options = {}
    writer = None
    if args.record:
        from ..recordings.capture import open_capture_tap

        writer = open_capture_tap(args.record, settings)
        options["tap"] = writer
    device = open_from_settings(settings, **options)
    try:
        ident = device.open()
        progress.done(
            f"connected: {settings.port} ({ident.transport}, firmware {ident.firmware or '?'}, "
            f"ASA {'/'.join(str(a) for a in ident.asa)})"
        )
        outcome = calibrate(
            device,
            settings,
            write=settings.write and not args.no_write,
            clock=time.monotonic,
            on_progress=lambda s: progress.show(_describe(s), time.monotonic()),
        )
    finally:
        device.close()
        if writer is not None:
            writer.close()
    s = outcome.session
    progress.done()
    report = outcome.to_dict()
    if args.json:
        print_json(report)
    else:
        _print_text(report)
    if s.status.value == "done":
        if outcome.verified or args.no_write or not device.abilities.store:
            return EXIT_OK
    if s.failure in ("timeout", "end_of_data") or (s.failure or "").startswith("gate:"):
        if not args.json:
            print(f"not calibrated: {s.failure_message}")
        return EXIT_GATE
    if not args.json:
        print(f"not calibrated: {s.failure_message}")
    return EXIT_WRITE if s.failure else EXIT_GATE


def _print_text(r: dict) -> None:
    cal = r["calibration"]
    if cal:
        o = cal["offset_ut"]
        unc = (r.get("uncertainty") or {}).get("offset_ut") or [float("nan")] * 3
        print(f"model      {r.get('model')}")
        print(f"offset     [{o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}] µT  ± [{unc[0]:.3f}, {unc[1]:.3f}, {unc[2]:.3f}] (1σ)")
        print(f"field      {cal['field_ut']:.3f} µT")
        w = cal["soft_iron"]
        for i, row in enumerate(w):
            print(("soft iron  " if i == 0 else "           ") + "  ".join(f"{v: .5f}" for v in row))
        q = r["quality"]
        print(f"quality    rms {q.get('rms_ut', float('nan')):.3f} µT, {q['kept']} samples kept of {q['samples']}, "
              f"coverage {100 * q['coverage']:.0f}%")
    if r["written"]:
        print("written    yes, and " + ("VERIFIED by read-back" if r["verified"] else "NOT verified"))
    elif cal and r["status"] == "done":
        print("written    no (--no-write or a read-only source)")
