"""``magcal stream --port URL [--calibrated] [--count N] [--rate HZ] [--json]``: print live
samples in µT, optionally with the device's stored calibration applied on the host.

Text: one line per sample, ``seq t_s x y z |h| temp_c``; rejected readings go to stderr.
``--json``: one JSON object per line, ``{"type": "sample", ...}`` or ``{"type": "event", ...}``.
Works for every backend through the generic Device API."""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from ..core.calibration import Calibration
from ..core.errors import DeviceError, NoReply
from ..core.events import Event
from ..core.sample import Sample
from ..devices import open_device
from ..devices.base import batches

HELP = "print live samples (µT), optionally calibrated with the stored calibration"


def add_arguments(p) -> None:
    p.add_argument("--port", required=True, help="device: i2c:1, /dev/ttyACM0, sim://, … (see magcal.devices)")
    p.add_argument("--dialect", default="native", choices=("native", "motioncal", "auto"))
    p.add_argument("--calibrated", action="store_true", help="apply the calibration stored for this device")
    p.add_argument("--count", type=int, default=0, help="stop after N samples (default: until Ctrl-C)")
    p.add_argument("--rate", type=int, default=None, help="measurement rate in Hz (default: the device's)")
    p.add_argument("--json", action="store_true", help="JSON lines instead of text")
    p.add_argument(
        "--stall-s", type=float, default=10.0, help="give up when no sample arrives for this long (default 10 s)"
    )


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
        return json.dumps({"type": "event", "kind": e.kind, "seq": e.seq, "count": e.count, "detail": e.detail})
    where = "" if e.seq is None else f" seq {e.seq}"
    return f"# {e.kind}{where}: {e.detail}".rstrip(": ")


def run(args) -> int:
    if args.count < 0:
        raise DeviceError(f"--count must be ≥ 0, not {args.count}")
    dev = open_device(args.port, dialect=args.dialect)
    shown = 0
    try:
        with dev:
            dev.open()
            cal = None
            if args.calibrated:
                cal = dev.read_calibration()
                if cal is None:
                    raise DeviceError(f"{args.port}: no calibration stored for this device (run `magcal calibrate` first)")
            if not args.json:
                head = "  seq        t_s         x         y         z       |h|  temp_c"
                print(head + ("   (calibrated)" if cal is not None else "   (µT, uncalibrated)"))
            dev.start(args.rate)
            last = time.monotonic()
            for items in batches(dev, 0.1):
                for item in items:
                    if isinstance(item, Sample):
                        if not item.valid:
                            continue
                        print(format_sample(item, apply(cal, item), args.json, cal is not None), flush=True)
                        shown += 1
                        last = time.monotonic()
                        if args.count and shown >= args.count:
                            break
                    elif isinstance(item, Event):
                        line = format_event(item, args.json)
                        print(line, file=sys.stdout if args.json else sys.stderr, flush=True)
                if args.count and shown >= args.count:
                    break
                if time.monotonic() - last > args.stall_s:
                    raise NoReply(f"{args.port}: no sample for {args.stall_s:g} s")
            dev.stop()
    except BrokenPipeError:  # `magcal stream | head`
        try:
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the flush at exit
        except OSError:
            pass
        return 0
    if not args.json:
        stats = ", ".join(f"{k} {v}" for k, v in sorted(dev.stats().items()))
        print(f"# {shown} samples; {stats}", file=sys.stderr)
    return 0
