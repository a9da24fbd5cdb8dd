"""``magcal calibrate``: connect, identify, stream, collect, fit, write back, read back, compare.

On a terminal it shows, live, the map of field directions seen and missing and which side of
the board to aim along the field next (``magcal.cli.coverage_map``), with the sample rate and
the time left. Exit status (``magcal.cli.exits``): 0 after a verified write (or, with
``--no-write``, after a fit that passed every gate); 3 when a gate was not met in time (the
message names it); 4 when the calibration was not written or not verified (refused, read back
different, or a read-only source such as ``replay://`` without ``--no-write``); 5 for the
device or port; 2 for usage (no device named, a bad option).

``--json`` prints ``magcal.calibrate/1``: ``status``, ``failure``, ``message``, ``model``,
``calibration`` {offset_ut, field_ut, soft_iron}, ``uncertainty``, ``rms_ut``, ``n_samples``
(received), ``n_kept`` (kept for the fit: at most 8 per direction cell, so no pose outweighs
another), ``n_used`` (fitted, after outliers), ``outliers``, ``coverage`` (share of the 128
direction cells), ``rate_hz`` (the rate the device took), ``measured_rate_hz``, ``gates``,
``written``, ``verified``, ``restored_previous``, ``device``, ``port``, ``counters``, ``link``.
"""

from __future__ import annotations

from .exits import Exit, exit_for
from .options import add

HELP = "calibrate a device end to end and write the result back (verified by read-back)"


def add_arguments(p) -> None:
    add(p, "port", "baud", "dialect", "config", "rate", "timeout", "model", "json", "quiet")
    p.add_argument("--no-write", action="store_true", help="fit and report, but do not write to the device")
    p.add_argument("--record", metavar="FILE", help="also keep the raw bytes as a capture (replay://FILE)")
    from .view import add_view_option

    add_view_option(p)


def _live(session, timeout_s: float, elapsed: float, colour: bool, guide=None) -> str:
    """The live display: a status line, the live estimate, the direction map with a legend for
    each of its glyphs, the gates waited on and the next move (pure). Each line is short enough
    for 80 columns, or is wrapped there between words (``Progress``), so no number is cut."""
    from ..logic.session import Status
    from .common import duration
    from .coverage_map import LEGEND, hint, render

    p = session.progress()
    kept = session.kept
    rate = p["samples"] / elapsed if elapsed > 0.5 else 0.0
    need = session.gates_cfg.min_coverage
    lines = [f"{p['status']}: {p['samples']} samples ({rate:.0f}/s), {100 * p['coverage']:.0f}% of directions "
             f"(need {100 * need:.0f}%), {len(kept)} kept, gives up in {duration(max(0, timeout_s - elapsed))}"]
    if p["offset_ut"]:
        o = p["offset_ut"]
        lines.append(f"  live {p['model']}: offset [{o[0]:.1f} {o[1]:.1f} {o[2]:.1f}] µT, |B| {p['field_ut']:.1f} µT")
    if session.status is Status.COLLECTING:
        direction = None
        if session.last_field_ut is not None:
            direction = session.last_field_ut - kept.centre_ut
        counts = kept.cell_counts()
        lines.append(render(counts, kept.per_cell, kept.bands, kept.sectors, direction, colour))
        lines.append("  " + LEGEND)
        lines.append(f"  waiting on: {', '.join(g.name for g in session.failing_gates()) or '—'}")
        lines += _next_move(guide, hint(counts, kept.bands, kept.sectors, direction))
    return "\n".join(lines)


def _next_move(guide, field_hint: str) -> list[str]:
    """What to do next: with an accelerometer, the side to lay the board on or to turn on and
    the six sides ticked off; without one, the field-relative hint — after "you are not
    moving" when the board has been still (``magcal.logic.guidance``) (pure)."""
    from ..logic.guidance import Nudge

    advice = guide.advice() if guide is not None else None
    if advice is None or advice.nudge is Nudge.FIELD_ONLY:
        still = advice is not None and advice.still
        return ["  " + ("you are not moving: " if still else "") + field_hint]
    return ["  " + advice.checklist, "  next: " + advice.text]


def _look(guide, session) -> None:
    """Show the guide where the board is now: the latest sample, about the kept centre."""
    s = session.last_sample
    if s is None or session.last_field_ut is None:
        return
    a = s.aux
    accel = (a["ax_g"], a["ay_g"], a["az_g"]) if "ax_g" in a else None
    guide.update(s.t_s, session.last_field_ut - session.kept.centre_ut, accel)


def run(args) -> int:
    import time

    from ..app.procedure import calibrate
    from ..logic.guidance import Guide
    from .common import Progress, device_settings, document, open_from_settings, print_json

    settings = device_settings(args, timeout_s=args.timeout, rate_hz=args.rate, model=args.model)
    progress = Progress(quiet=args.quiet)
    options, writer = {}, None
    if args.record:
        from ..recordings.capture import open_capture_tap

        writer = open_capture_tap(args.record, settings)
        options["tap"] = writer
    device = open_from_settings(settings, **options)
    view, outcome = _view(args, settings), None
    try:
        ident = device.open()
        progress.done(f"connected: {settings.port} ({ident.transport}, firmware {ident.firmware or '?'}, "
                      f"ASA {'/'.join(str(a) for a in ident.asa)})")
        progress.t0 = time.monotonic()
        guide = Guide(chip=ident.chip)  # names the sides in the IMU axes (None: a MotionCal board, one frame)
        outcome = calibrate(
            device, settings, write=settings.write and not args.no_write, clock=time.monotonic,
            on_progress=lambda s: (_look(guide, s),
                                   progress.show(_live(s, settings.timeout_s, progress.elapsed(), progress.active,
                                                       guide)),
                                   view and view.progress(s)),
            **({"progress_every_s": view.every_s} if view else {}),
        )
    finally:
        if view:
            view.finish(outcome)
        device.close()
        if writer is not None:
            writer.close()
    progress.clear()
    report = document("calibrate", {**outcome.to_dict(), "port": settings.port})
    code = exit_status(outcome, args.no_write)
    if args.json:
        print_json(report)
    else:
        print(format_text(report))
        if code == Exit.WRITE and not device.abilities.store and not report["failure"]:
            print(f"not written: {settings.port} is a read-only source (add --no-write when that is intended)")
        elif code != Exit.OK:
            print(f"not calibrated: {report['message']}")
    return code


def _view(args, settings):
    """The live view in the browser (``--view``): started before the device opens, so the URL
    is on screen while the board is found (``magcal.cli.view``)."""
    if not args.view:
        return None
    from .view import LiveView, start

    return LiveView(start(args.json), settings.timeout_s)


def exit_status(outcome, no_write: bool) -> Exit:
    """0 only for a verified write (or a passed fit with --no-write); 3 when the data did not
    pass; 4 when the calibration did not reach the device as sent (``exits.exit_for``)."""
    from ..logic.session import Status

    s = outcome.session
    if s.status is Status.DONE:
        return Exit.OK if (outcome.verified or no_write) else Exit.WRITE
    return exit_for(s.failure)


def format_text(r: dict) -> str:
    """The human-readable result (pure)."""
    cal = r["calibration"]
    chip = (r.get("device") or {}).get("chip")
    lines = [f"chip       {chip}"] if chip else []
    if cal:
        o = cal["offset_ut"]
        unc = (r.get("uncertainty") or {}).get("offset_ut") or [float("nan")] * 3
        lines.append(f"model      {r.get('model')}")
        lines.append(f"offset     [{o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}] µT  ± [{unc[0]:.3f}, {unc[1]:.3f}, "
                     f"{unc[2]:.3f}] (1σ)")
        lines.append(f"field      {cal['field_ut']:.3f} µT")
        for i, row in enumerate(cal["soft_iron"]):
            lines.append(("soft iron  " if i == 0 else "           ") + "  ".join(f"{v: .5f}" for v in row))
        n_out = len(r.get("outliers") or [])
        lines.append(f"rms_ut     {r['rms_ut']:.3f}")
        lines.append(f"samples    {r['n_samples']} received at {_rate(r)}")
        lines.append(f"           {r['n_kept']} kept (at most 8 per direction cell: no pose outweighs another)")
        lines.append(f"           {r['n_used']} fitted after {n_out} outlier(s)")
        lines.append(f"coverage   {100 * r['coverage']:.0f}% of directions")
    if r["written"]:
        lines.append("written    yes, and " + ("VERIFIED by read-back" if r["verified"] else "NOT verified"))
    elif cal and r["status"] == "done":
        lines.append("written    no")
    return "\n".join(lines)


def _rate(r: dict) -> str:
    asked = f"{r['rate_hz']} Hz" if r.get("rate_hz") else "the device's rate"
    got = r.get("measured_rate_hz")
    return asked + (f" ({got:.1f} per second arrived)" if got else "")
