"""Options and output helpers shared by the subcommands."""

from __future__ import annotations

import json
import sys

from ..app import config


def add_port_options(p, default_port: bool = True) -> None:
    p.add_argument("--port", help="device: serial port or URL (/dev/ttyACM0, COM3, socket://…), "
                   "sim://, emu://, replay://FILE, i2c:1 (default from config: sim://)")
    p.add_argument("--baud", type=int, help="serial baud rate (default 115200)")
    p.add_argument("--dialect", choices=("native", "motioncal", "auto"),
                   help="wire convention: magcal protocol v1, the MotionCal/Adafruit Raw: lines, or detect")


def add_config_option(p) -> None:
    p.add_argument("--config", metavar="FILE", help="YAML settings (see config/magcal.yaml)")


def add_json_option(p) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def load_settings(args, **extra):
    overrides = {
        "port": getattr(args, "port", None),
        "baud": getattr(args, "baud", None),
        "dialect": getattr(args, "dialect", None),
    }
    overrides.update(extra)
    return config.load(getattr(args, "config", None), overrides)


def open_from_settings(settings, **options):
    from ..devices import open_device

    kw = dict(options)
    if settings.baud != 115200:
        kw["baud"] = settings.baud
    return open_device(settings.port, dialect=settings.dialect, **kw)


def add_table_options(p) -> None:
    """How to read a recording that is someone else's table (CSV, tab- or space-separated)."""
    g = p.add_argument_group("reading a table", "for CSV or other delimited text that is not magcal's own")
    g.add_argument("--columns", metavar="X,Y,Z",
                   help="the magnetometer columns: header names or 1-based positions (default: mx,my,mz, "
                   "else mag_x… or magX… style names)")
    g.add_argument("--unit", metavar="UNIT",
                   help="unit of those columns: uT, nT, mG, gauss, tesla, or the µT of one count "
                   "(default: from the column names, else µT)")
    g.add_argument("--time", metavar="COLUMN", help="the time column, name or 1-based position (default: t, time …)")
    g.add_argument("--time-unit", choices=("s", "ms", "us"),
                   help="unit of the time column (default: from its name, else s)")
    g.add_argument("--channels", metavar="A,B,…",
                   help="keep only these columns as channels (candidate covariates); '' for none "
                   "(default: every other numeric column but a second magnetometer's)")
    g.add_argument("--temp", metavar="COLUMN", help="the die temperature column in °C (read as temp_c)")
    g.add_argument("--current", metavar="COLUMN", help="the interfering current column in A (read as current_a)")
    g.add_argument("--delimiter", metavar="C",
                   help="column separator (default: found from the first line; 'tab' or 'space' for those)")


def table_format(args):
    """The TableFormat the table options ask for (all None when none were given)."""
    from ..recordings.table import TableFormat

    columns = None
    if args.columns is not None:
        columns = tuple(c.strip() for c in args.columns.split(","))
    delimiter = {"tab": "\t", "space": " "}.get(args.delimiter, args.delimiter)
    channels = None if args.channels is None else tuple(c.strip() for c in args.channels.split(",") if c.strip())
    return TableFormat(columns=columns, unit=args.unit, time=args.time, time_unit=args.time_unit,
                       delimiter=delimiter, channels=channels, temp=args.temp, current=args.current)


def field_warning(field_ut: float) -> list[str]:
    """Warn (on stderr, and as a list for JSON) when a fitted field is no Earth field."""
    from ..recordings.table import plausible_field

    w = plausible_field(field_ut)
    if w is None:
        return []
    print(f"magcal: warning: {w}", file=sys.stderr)
    return [w]


def print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=2, allow_nan=False, default=_default)
    sys.stdout.write("\n")
    sys.stdout.flush()


def _default(o):
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


class Progress:
    """A one-line live display on a terminal; occasional lines when not a terminal."""

    def __init__(self, stream=None, quiet: bool = False):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.quiet = quiet
        self._last_line = 0.0
        self._open = False

    def show(self, text: str, now: float) -> None:
        if self.quiet:
            return
        if self.tty:
            self.stream.write("\r\033[K" + text)
            self._open = True
        elif now - self._last_line >= 2.0:
            self._last_line = now
            self.stream.write(text + "\n")
        self.stream.flush()

    def done(self, text: str = "") -> None:
        if self.quiet:
            return
        if self._open:
            self.stream.write("\n")
            self._open = False
        if text:
            self.stream.write(text + "\n")
        self.stream.flush()
