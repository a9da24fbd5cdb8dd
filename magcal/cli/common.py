"""Options and output helpers shared by the subcommands."""

from __future__ import annotations

import json
import sys

from ..core.errors import ConfigError


def load_settings(args, **extra):
    overrides = {
        "port": getattr(args, "port", None),
        "baud": getattr(args, "baud", None),
        "dialect": getattr(args, "dialect", None),
    }
    overrides.update(extra)
    from ..app import config

    settings = config.load(getattr(args, "config", None), overrides)
    if getattr(args, "baud", None) is not None and not _serial(settings.port):
        raise ConfigError(f"--baud applies to serial ports; {settings.port} has no baud rate (leave --baud out)")
    return settings


def _serial(port: str) -> bool:
    from ..devices import scheme_of

    return scheme_of(port) == "serial"


def device_settings(args, **extra):
    """The settings of a device command, with a port (named, the one plugged in, or asked)."""
    from .ports import with_port

    return with_port(load_settings(args, **extra))


def open_from_settings(settings, **options):
    """The device the settings name; ``baud`` (a serial-port setting) only goes to a serial port."""
    from ..devices import open_device

    kw = dict(options)
    if settings.baud != 115200 and _serial(settings.port):
        kw["baud"] = settings.baud
    return open_device(settings.port, dialect=settings.dialect, **kw)


def field_warning(field_ut: float) -> list[str]:
    """Warn (on stderr, and as a list for JSON) when a fitted field is no Earth field."""
    from ..recordings.table import plausible_field

    w = plausible_field(field_ut)
    if w is None:
        return []
    print(f"magcal: warning: {w}", file=sys.stderr)
    return [w]


def calibration_lines(c: dict, u: dict | None = None) -> list[str]:
    """The offset_ut, field_ut and soft_iron rows of a calibration dict, each with ± 1σ when the
    uncertainty dict ``u`` is given (pure)."""

    def pm(key: str, fmt: str, row: int | None = None) -> str:
        v = (u or {}).get(key)
        if v is None:
            return ""
        v = v if row is None else v[row]
        return "   ± " + (" ".join(format(x, fmt) for x in v) if isinstance(v, (list, tuple)) else format(v, fmt))

    widened = (u or {}).get("autocorrelation_factor", 1.0) or 1.0
    lines = ["offset_ut   " + " ".join(f"{v:9.3f}" for v in c["offset_ut"]) + pm("offset_ut", ".3f")
             + (f"   (widened ×{widened:.1f}: the residuals are correlated in time)" if widened >= 1.5 else ""),
             f"field_ut    {c['field_ut']:9.3f}" + pm("field_ut", ".3f")]
    for i, row in enumerate(c.get("soft_iron") or []):
        lines.append(("soft_iron   " if i == 0 else "            ") + " ".join(f"{v:9.5f}" for v in row)
                     + pm("soft_iron", ".5f", i))
    return lines


def document(command: str, body: dict, version: int = 1) -> dict:
    """The JSON object a command prints: ``schema`` names its shape and version first."""
    return {"schema": f"magcal.{command}/{version}", **body}


# what reading a recording met that changes what is in it: counter → how to say it
_READING_WORDS = {
    "calibrated_lines": "calibrated (U) lines left out (not raw readings)",
    "duplicate_lines": "duplicate or late lines taken once",
    "out_of_sequence_lines": "out-of-sequence lines left out",
    "sequence_resyncs": "renumberings without a hello",
    "lost_lines": "lines lost (sequence gaps)",
    "hellos_refused": "hellos with a changed identity refused",
    "damaged_chunks": "damaged capture chunks",
    "skipped_bytes": "capture bytes skipped at damage",
    "truncated_bytes": "bytes of a cut-off last chunk",
    "bad_checksums": "lines with a bad checksum",
    "torn_lines": "torn lines",
    "overlong_lines": "over-long lines",
    "malformed_lines": "malformed lines",
    "bad_syntax": "lines with bad fields",
    "unknown_types": "lines of unknown type",
}
_READING_NOTES = {"thinned_every": "a long recording: the fit uses every {} sample"}


def ordinal(k: int) -> str:
    """2nd, 3rd, 4th, 11th, 12th, 21st …"""
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


def reading_report(series, path) -> dict:
    """What reading ``path`` met (``Series.reading``) for the JSON ``reading`` key; when any
    of it left something out or found damage, one warning line on stderr says what."""
    r = dict(series.reading)
    said = [f"{r[k]} {w}" for k, w in _READING_WORDS.items() if r.get(k)]
    if said:
        print(f"magcal: warning: {path}: " + "; ".join(said), file=sys.stderr)
    for k, note in _READING_NOTES.items():
        if r.get(k):
            print(f"magcal: note: {path}: " + note.format(ordinal(r[k])) + f" ({len(series)} of {r['samples_read']}; "
                  "its uncertainty is that of the samples used)", file=sys.stderr)
    return r


def print_json(obj) -> None:
    json.dump(finite_or_null(obj), sys.stdout, indent=2, allow_nan=False, default=_default)
    sys.stdout.write("\n")
    sys.stdout.flush()


def finite_or_null(obj):
    """``obj`` with every NaN or infinity as None (pure): JSON has no such numbers, and a
    quantity the data could not determine (a held-out figure of a refit that failed, a size over
    a floor of zero) is ``null`` in every document, never a crash after the work is done."""
    import numpy as np

    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_or_null(obj.tolist())
    if isinstance(obj, (float, np.floating)) and not np.isfinite(obj):
        return None
    return obj


def _default(o):
    import numpy as np

    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def duration(s: float) -> str:
    """``42 s``, ``3:07``, ``1:02:03`` (pure)."""
    s = max(0, int(round(s)))
    if s < 60:
        return f"{s} s"
    h, rem = divmod(s, 3600)
    return f"{h}:{rem // 60:02d}:{rem % 60:02d}" if h else f"{rem // 60}:{rem % 60:02d}"


def rate_eta(done: float, total: float | None, elapsed: float, unit: str) -> str:
    """``12 345/50 000 samples  4 210/s  ETA 9 s`` — what is done, how fast, how long to go (pure)."""
    rate = done / elapsed if elapsed > 0 else 0.0
    text = f"{done:,.0f}" + (f"/{total:,.0f}" if total else "") + f" {unit}"
    if elapsed >= 0.5:
        text += f"  {rate:,.0f}/s"
    if total and rate > 0 and done < total:
        text += f"  ETA {duration((total - done) / rate)}"
    return text.replace(",", " ")


def clip(line: str, width: int) -> str:
    """``line`` cut to ``width`` visible characters (colour escapes kept, not counted) (pure)."""
    import re

    out, seen = [], 0
    for part in re.split(r"(\033\[[0-9;]*m)", line):
        if part.startswith("\033["):
            out.append(part)
            continue
        room = width - seen
        if room <= 0:
            continue
        out.append(part[:room])
        seen += min(len(part), room)
    return "".join(out)


def stream_columns(stream, fallback: int = 80) -> int:
    """The width of the terminal ``stream`` is on (not stdout's: ``diagnose --json > d.json``
    draws on stderr); ``COLUMNS`` when set, else ``fallback`` when it is no terminal."""
    import os

    if os.environ.get("COLUMNS", "").isdigit():
        return max(20, int(os.environ["COLUMNS"]))
    try:
        return max(20, os.get_terminal_size(stream.fileno()).columns)
    except (AttributeError, OSError, ValueError):
        return fallback


def wrap_visible(line: str, width: int) -> list[str]:
    """``line`` as lines of at most ``width`` visible characters (colour escapes not counted),
    broken at spaces so no number is cut; the continuation indented two spaces more than the
    line. A single word longer than the width is broken, not cut (pure)."""
    import re

    visible = len(re.sub(r"\033\[[0-9;]*m", "", line))
    if visible <= width:
        return [line]
    indent = " " * (len(line) - len(line.lstrip(" ")) + 2)
    out, cur, cur_len = [], "", 0
    for piece in re.findall(r"\s*\S+", line):  # each word with the spaces before it
        p_len = len(re.sub(r"\033\[[0-9;]*m", "", piece))
        if cur and cur_len + p_len > width:
            out.append(cur)
            cur = indent + piece.lstrip(" ")
            cur_len = len(indent) + p_len - (len(piece) - len(piece.lstrip(" ")))
        else:
            cur, cur_len = cur + piece, cur_len + p_len
    out.append(cur)
    return [piece for part in out for piece in _break_word(part, width)]


def _break_word(part: str, width: int) -> list[str]:
    """A line still wider than ``width`` (one long word, such as a path): broken into pieces
    of ``width`` characters, none lost; clipped only when it carries colour escapes (pure)."""
    if len(part) <= width or width < 1:
        return [part]
    if "\033[" in part:
        return [clip(part, width)]
    return [part[i:i + width] for i in range(0, len(part), width)]


class Progress:
    """A live display on stderr, redrawn in place (one or several lines). Silent when stderr is
    not a terminal or with ``quiet``: a log or a pipe gets only the results."""

    def __init__(self, quiet: bool = False, stream=None, clock=None, every_s: float = 0.1):
        import time

        self.stream = stream or sys.stderr
        self.clock = clock or time.monotonic
        self.active = not quiet and self.stream.isatty()
        self.every_s = every_s
        self.t0 = self.clock()
        self._drawn = 0  # lines on screen
        self._last = -1e9

    def elapsed(self) -> float:
        return self.clock() - self.t0

    def show(self, text: str, force: bool = False) -> None:
        if not self.active:
            return
        now = self.clock()
        if not force and now - self._last < self.every_s:
            return
        self._last = now
        width = stream_columns(self.stream) - 1
        lines = [part for line in text.split("\n") for part in wrap_visible(line, width)]
        up = f"\033[{self._drawn - 1}A" if self._drawn > 1 else ""
        self.stream.write("\r" + up + "\033[J" + "\n".join(lines))
        self._drawn = len(lines)
        self.stream.flush()

    def count(self, label: str, done: float, total: float | None = None, unit: str = "samples") -> None:
        """One line: ``label  done/total unit  rate/s  ETA``."""
        self.show(f"{label}  {rate_eta(done, total, self.elapsed(), unit)}")

    def done(self, text: str = "") -> None:
        """Leave the last display on screen and go on below it (``text`` printed if given)."""
        if self._drawn:
            self.stream.write("\n")
            self._drawn = 0
        if text:
            lines = wrap_visible(text, stream_columns(self.stream) - 1) if self.active else [text]
            self.stream.write("\n".join(lines) + "\n")
        self.stream.flush()

    def working(self, label: str):
        """A context manager for work that reports no progress of its own: the display ticks
        (label, elapsed time) from a thread until the work is done; ``step(i, n, name)`` on
        what it returns adds the step and an ETA from the steps' pace."""
        return _Ticker(self, label)

    def clear(self) -> None:
        """Remove the display."""
        if self._drawn and self.active:
            up = f"\033[{self._drawn - 1}A" if self._drawn > 1 else ""
            self.stream.write("\r" + up + "\033[J")
            self.stream.flush()
        self._drawn = 0


class _Ticker:
    """What ``Progress.working`` returns: a thread that redraws the label and the elapsed time
    on a clock until the work ends, whatever the work reports."""

    SHOW_AFTER_S = 1.0  # work done within a second draws nothing: no display flashes past

    def __init__(self, progress: Progress, label: str):
        import threading

        self.progress, self.label = progress, label
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.t0 = progress.clock()
        self.counted, self.what = "", ""
        self.total_s = None  # the expected whole, once a share is known

    def step(self, i: int, n: int, name: str) -> None:
        """Step ``i`` of ``n`` (0-based, steps of like size) begins: ETA from the pace so far."""
        elapsed = self.progress.clock() - self.t0
        eta = f", ETA {duration(elapsed * (n - i) / i)}" if i > 0 and elapsed > 1 else ""
        self.total_s = None  # an earlier share's whole no longer applies: the steps' pace does
        self.counted = f"  [{i + 1}/{n}{eta}]"

    def doing(self, what: str) -> None:
        """What the work is doing now (no ETA of its own: its parts are not alike; an earlier
        share's ETA would be stale, so none is shown until a share or a step gives one)."""
        self.what = f"  {what}"
        self.total_s = None

    def share(self, done: float, what: str) -> None:
        """``done`` (0…1) of the work is behind, by a known share per step: the ETA follows
        from the pace so far (and counts down while a step runs)."""
        elapsed = self.progress.clock() - self.t0
        self.total_s = elapsed / done if done > 0.05 and elapsed > 0.5 else None
        self.what = f"  {what} ({100 * done:.0f} % done)"

    def _run(self) -> None:
        spin = "|/-\\"
        k = 0
        while not self.stop.wait(0.2):
            k += 1
            elapsed = self.progress.clock() - self.t0
            if elapsed >= self.SHOW_AFTER_S:
                eta = ""
                if self.total_s is not None:
                    left = self.total_s - elapsed
                    eta = f"  ETA {duration(left)}" if left >= 1 else "  finishing"
                self.progress.show(f"{spin[k % 4]} {self.label}  {duration(elapsed)}{self.counted}{self.what}{eta}",
                                   force=True)

    def __enter__(self):
        if self.progress.active:
            self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        if self.thread.is_alive():
            self.thread.join()
        self.progress.clear()
