"""``magcal record [--port URL] -o FILE [--seconds S] [--count N] [--rate HZ] [--json]``: keep the
raw bytes a device sends, with receive times, as a capture (``magcal.recordings.capture``).

Everything the link reads from the moment the port opens is recorded — the hello, the replies,
every sample and every defect — so ``replay://FILE`` and ``magcal fit FILE`` see exactly what
the live link saw. Stops after S seconds, N samples, the end of a finite source, or Ctrl-C
(the capture stays valid). On a terminal it shows the samples so far, their rate and the time
left. Prints a summary; ``--json`` as ``magcal.record/1``.
"""

from __future__ import annotations

import contextlib
import os
import time

from ..core.errors import ConfigError
from ..core.events import Event
from ..core.sample import Sample
from ..devices.base import batches
from ..recordings.capture import CaptureWriteError, open_capture_tap
from ..recordings.capture_cut import keep_first_samples
from .common import Progress, device_settings, document, open_from_settings, print_json
from .exits import Exit
from .options import add

HELP = "record the raw bytes from a device (with receive times) as a capture file"


def add_arguments(p) -> None:
    add(p, "port", "baud", "dialect", "config")
    add(p, "output", required=True, help="capture file to write (read it with replay://FILE, fit, diagnose)")
    add(p, "seconds", "count", "rate", "json", "quiet")


def _stop_after(args) -> tuple[float | None, str]:
    """(the total to show progress against, its unit): samples or seconds (pure)."""
    if args.count is not None:
        return float(args.count), "samples"
    return args.seconds, "s"


def _read_loop(dev, args, progress, counts) -> str:
    """Read until told to stop; count samples, gaps and resets; say why it stopped."""
    t0 = time.monotonic()
    total, unit = _stop_after(args)
    try:
        for items in batches(dev, 0.1):
            for it in items:
                if isinstance(it, Sample):
                    if counts["samples"] == args.count:
                        return "done"  # a read that brought more than asked for: N means N
                    counts["samples"] += 1
                elif isinstance(it, Event) and it.kind in ("gap", "reset"):
                    counts[it.kind + "s"] += 1
            elapsed = time.monotonic() - t0
            if (args.count is not None and counts["samples"] >= args.count) or (
                    args.seconds is not None and elapsed >= args.seconds):
                return "done"
            done = counts["samples"] if unit == "samples" else elapsed
            progress.show(f"recording {args.output}  {counts['samples']} samples  "
                          + _progress_text(done, total, unit, elapsed, counts["samples"]))
    except CaptureWriteError as exc:
        return str(exc)
    return "end of source"


def _progress_text(done, total, unit, elapsed, samples) -> str:
    from .common import duration

    rate = f"{samples / elapsed:.0f} samples/s" if elapsed > 0.5 else ""
    left = ""
    if total and unit == "s":
        left = f"  {duration(total - done)} left"
    elif total and samples and elapsed > 0.5:
        left = f"  ETA {duration((total - done) / (samples / elapsed))}"
    return f"{rate}  {duration(elapsed)} elapsed{left}"


def _recount(writer) -> None:
    """After a cut, the writer's counts are those of the file as it now is."""
    from ..recordings.capture import CaptureReader

    kept = CaptureReader(writer.path)
    writer.chunks, writer.bytes_recorded = len(kept), sum(len(chunk) for _, chunk in kept)


def run(args) -> int:
    if args.seconds is None and args.count is None:
        raise ConfigError("say when to stop: --seconds S and/or --count N")
    settings = device_settings(args, rate_hz=args.rate)
    writer = open_capture_tap(args.output, settings)
    counts = {"samples": 0, "gaps": 0, "resets": 0}
    progress = Progress(quiet=args.quiet)
    t0 = time.monotonic()
    try:
        dev = open_from_settings(settings, tap=writer)
    except Exception:  # nothing was read: leave no empty capture behind
        writer.close()
        with contextlib.suppress(OSError):
            os.remove(args.output)
        raise
    ident = None
    try:
        ident = dev.open()
        dev.start(settings.rate_hz)
        ident = dev.identity  # with the rate the device took
        stopped = _read_loop(dev, args, progress, counts)
        with contextlib.suppress(Exception):  # the summary matters more than a polite stop
            dev.stop()
    except KeyboardInterrupt:
        stopped = "interrupted"
        ident = dev.identity
    finally:
        dev.close()
        writer.close()
        progress.clear()
    if args.count is not None and writer.error is None:
        if keep_first_samples(writer.path, args.count):
            _recount(writer)
    samples, gaps, resets = counts["samples"], counts["gaps"], counts["resets"]
    summary = document("record", {
        "file": writer.path,
        "port": settings.port,
        "elapsed_s": round(time.monotonic() - t0, 3),
        "n_samples": samples,
        "gaps": gaps,
        "resets": resets,
        "stopped": stopped,
        "device": ident.to_dict() if ident else None,
        "capture": writer.stats(),
        "rate_hz": ident.rate_hz if ident and ident.rate_hz else None,
        "link": dev.stats(),
    })
    if args.json:
        print_json(summary)
    else:
        print(f"recorded {samples} samples ({writer.bytes_recorded} bytes in {writer.chunks} chunks) "
              f"from {settings.port} in {summary['elapsed_s']:.1f} s -> {writer.path}")
        if gaps or resets:
            print(f"link: {gaps} gaps, {resets} device resets")
        if stopped not in ("done", "end of source"):
            print(f"stopped: {stopped}")
    return Exit.OK if writer.error is None else Exit.INPUT
