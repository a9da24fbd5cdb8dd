"""``magcal record --port URL -o FILE [--seconds S] [--count N] [--baud B] [--rate HZ] [--json]``:
keep the raw bytes a device sends, with receive times, as a capture (``magcal.recordings.capture``).

Everything the link reads from the moment the port opens is recorded — the hello, the replies,
every sample and every defect — so ``replay://FILE`` and ``magcal fit FILE`` see exactly what
the live link saw. Stops after S seconds, N samples, the end of a finite source, or Ctrl-C
(the capture stays valid). Prints a summary; ``--json`` as one object.
"""

from __future__ import annotations

import contextlib
import os
import time

from ..core.errors import InputError
from ..core.events import Event
from ..core.sample import Sample
from ..devices import open_device, scheme_of
from ..devices.base import batches
from ..recordings.capture import CaptureWriteError, CaptureWriter, make_header
from .common import print_json

HELP = "record the raw bytes from a device (with receive times) as a capture file"


def add_arguments(p) -> None:
    p.add_argument("--port", required=True, help="device: /dev/ttyACM0, COM3, socket://…, sim://, emu://, replay://FILE")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="capture file to write")
    p.add_argument("--seconds", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--count", type=int, default=None, help="stop after this many samples")
    p.add_argument("--baud", type=int, default=None, help="serial baud rate (default 115200)")
    p.add_argument("--rate", type=int, default=None, help="measurement rate in Hz (default: the device's)")
    p.add_argument("--dialect", default="native", choices=("native", "motioncal", "auto"),
                   help="wire convention: protocol v1, a MotionCal/Adafruit sketch's Raw: lines, or detect")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def run(args) -> int:
    if args.seconds is None and args.count is None:
        raise InputError("say when to stop: --seconds S and/or --count N")
    if (args.seconds is not None and args.seconds <= 0) or (args.count is not None and args.count <= 0):
        raise InputError("--seconds and --count must be positive")
    options = {}
    if args.baud is not None and scheme_of(args.port) == "serial":
        options["baud"] = args.baud
    writer = CaptureWriter(args.output, make_header(args.port, args.baud or 115200, args.dialect))
    samples = gaps = resets = 0
    stopped = "done"
    t0 = time.monotonic()
    try:
        dev = open_device(args.port, dialect=args.dialect, tap=writer, **options)
    except Exception:  # nothing was read: leave no empty capture behind
        writer.close()
        with contextlib.suppress(OSError):
            os.remove(args.output)
        raise
    try:
        ident = dev.open()
        dev.start(args.rate)
        stopped = "end of source"
        try:
            for items in batches(dev, 0.1):
                samples += sum(isinstance(it, Sample) for it in items)
                gaps += sum(isinstance(it, Event) and it.kind == "gap" for it in items)
                resets += sum(isinstance(it, Event) and it.kind == "reset" for it in items)
                if (args.count is not None and samples >= args.count) or (
                        args.seconds is not None and time.monotonic() - t0 >= args.seconds):
                    stopped = "done"
                    break
        except CaptureWriteError as exc:
            stopped = str(exc)
        try:
            dev.stop()
        except Exception:  # the summary matters more than a polite stop
            pass
    except KeyboardInterrupt:
        stopped = "interrupted"
        ident = dev.identity
    finally:
        dev.close()
        writer.close()
    summary = {
        "file": writer.path,
        "port": args.port,
        "seconds": round(time.monotonic() - t0, 3),
        "samples": samples,
        "gaps": gaps,
        "resets": resets,
        "stopped": stopped,
        "identity": ident.to_dict() if ident else None,
        "capture": writer.stats(),
        "link": dev.stats(),
    }
    if args.json:
        print_json(summary)
    else:
        print(f"recorded {samples} samples ({writer.bytes_recorded} bytes in {writer.chunks} chunks) "
              f"from {args.port} in {summary['seconds']:.1f} s -> {writer.path}")
        if gaps or resets:
            print(f"link: {gaps} gaps, {resets} device resets")
        if stopped not in ("done", "end of source"):
            print(f"stopped: {stopped}")
    return 0 if writer.error is None else 1
