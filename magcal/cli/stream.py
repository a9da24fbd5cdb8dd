"""``magcal stream [--port URL] [--calibrated] [--count N] [--seconds S] [--rate HZ] [--json]``:
print live samples in µT, optionally with the device's stored calibration applied on the host.

Text: one line per sample, ``seq t_s x y z |h| temp_c``; rejected readings go to stderr.
``--json``: one JSON object per line (``magcal.stream/1``), ``{"schema": …, "type": "sample",
...}`` or ``{"schema": …, "type": "event", ...}``. Works for every backend through the generic
Device API. The output itself shows progress, so there is no other display."""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from ..core.calibration import Calibration
from ..core.errors import NoReply
from ..core.events import Event
from ..core.sample import Sample
from ..devices.base import batches
from .common import device_settings, open_from_settings
from .options import add, add_alias, positive

SCHEMA = "magcal.stream/1"

HELP = "print live samples (µT), optionally calibrated with the stored calibration"


def add_arguments(p) -> None:
    add(p, "port", "baud", "dialect", "config")
    p.add_argument("--calibrated", action="store_true", help="apply the calibration stored for this device")
    add(p, "count", help="stop after N samples (default: until Ctrl-C)")
    add(p, "seconds", help="stop after S seconds (default: until Ctrl-C)")
    add(p, "rate")
    add(p, "json", help="one JSON object per line (\"schema\": magcal.stream/1) instead of text")
    p.add_argument("--stall-timeout", type=positive, default=10.0, metavar="S", dest="stall_s",
                   help="give up when no sample arrives for S seconds")
    add_alias(p, "--stall-s", dest="stall_s", type=positive)


def apply(cal: Calibration | None, s: Sample) -> np.ndarray:
    """The sample's field in µT, corrected by ``cal`` when given (pure)."""
    m = np.asarray(s.field_ut, dtype=np.float64)
    if cal is None:
        return m
    channels = {"t_s": np.array([s.t_s])}
    if s.temp_c is not None:
        channels["temp_c"] = np.array([s.temp_c])
    for name, value in s.aux.items():
        channels[name] = np.array([value])
    return cal.correct(m, channels)[0]


def format_sample(s: Sample, h: np.ndarray, as_json: bool, calibrated: bool) -> str:
    if as_json:
        d = {
            "schema": SCHEMA,
            "type": "sample",
            "seq": s.seq,
            "t_s": round(s.t_s, 6),
            "field_ut": [round(float(v), 4) for v in h],
            "norm_ut": round(float(np.linalg.norm(h)), 4),
            "calibrated": calibrated,
        }
        if s.raw is not None:
            d["raw"] = list(s.raw)
        if s.temp_c is not None:
            d["temp_c"] = round(s.temp_c, 3)
        d.update({k: v for k, v in s.aux.items()})
        return json.dumps(d)
    temp = "" if s.temp_c is None else f" {s.temp_c:7.2f}"
    return f"{s.seq:5d} {s.t_s:10.3f} {h[0]:9.3f} {h[1]:9.3f} {h[2]:9.3f} {np.linalg.norm(h):9.3f}{temp}"


def format_event(e: Event, as_json: bool) -> str:
    if as_json:
        return json.dumps({"schema": SCHEMA, "type": "event", "kind": e.kind, "seq": e.seq, "count": e.count, "detail": e.detail})
    where = "" if e.seq is None else f" seq {e.seq}"
    return f"# {e.kind}{where}: {e.detail}".rstrip(": ")


def _pump(dev, args, cal, port: str) -> int:
    """Print samples until the count, the time or the source runs out; the number shown."""
    shown = 0
    t0 = last = time.monotonic()
    for items in batches(dev, 0.1):
        for item in items:
            if isinstance(item, Sample) and item.valid and not (args.count and shown >= args.count):
                print(format_sample(item, apply(cal, item), args.json, cal is not None), flush=True)
                shown += 1
                last = time.monotonic()
            elif isinstance(item, Event):
                print(format_event(item, args.json), file=sys.stdout if args.json else sys.stderr, flush=True)
        now = time.monotonic()
        if (args.count and shown >= args.count) or (args.seconds is not None and now - t0 >= args.seconds):
            break
        if now - last > args.stall_s:
            raise NoReply(f"{port}: no sample for {args.stall_s:g} s")
    return shown


def run(args) -> int:
    from .exits import Exit

    settings = device_settings(args, rate_hz=args.rate)
    dev = open_from_settings(settings)
    try:
        with dev:
            dev.open()
            record = dev.read_stored() if args.calibrated else None
            cal = None if record is None else record.calibration
            if args.calibrated and cal is None:
                what = (f"no usable calibration (the stored record cannot be used: {record.problem})"
                        if record.problem else "no calibration stored for this device")
                print(f"magcal stream: {settings.port}: {what} (run `magcal calibrate` first)", file=sys.stderr)
                return Exit.NO
            if not args.json:
                head = "  seq        t_s         x         y         z       |h|  temp_c"
                print(head + ("   (calibrated)" if cal is not None else "   (µT, uncalibrated)"))
            dev.start(settings.rate_hz)
            shown = _pump(dev, args, cal, settings.port)
            dev.stop()
    except BrokenPipeError:  # `magcal stream | head`
        try:
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the flush at exit
        except OSError:
            pass
        return Exit.OK
    if not args.json:
        stats = ", ".join(f"{k} {v}" for k, v in sorted(dev.stats().items()))
        print(f"# {shown} samples; {stats}", file=sys.stderr)
    return Exit.OK
