"""The one vocabulary of command-line options, and the typed parsers behind them.

Every command builds its options from here, so an option means the same thing, takes the same
unit and is checked the same way wherever it appears::

    from .options import add
    add(p, "port", "baud", "dialect", "config", "json", "quiet")
    add(p, "seconds", help="stop after S seconds")        # help may be sharpened per command

The typed parsers (``finite``, ``positive``, ``positive_int``, ``fraction``, ``rate_hz``,
``floats(3)``, ``existing_file``, ``output_file`` …) are ``type=`` callables for argparse: a
bad value becomes a usage error (exit 2) that names the option, the rule and the value. Each
one is also a plain function of a string, usable wherever text must become a checked value.
"""

from __future__ import annotations

import argparse
import math
import os

# -- typed parsers ----------------------------------------------------------------------------


def _fail(rule: str, text) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(f"must be {rule}, got {text!r}")


def finite(text) -> float:
    """A finite number (``nan`` and ``inf`` are refused)."""
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise _fail("a number", text) from None
    if not math.isfinite(v):
        raise _fail("a finite number", text)
    return v


def integer(text) -> int:
    """A whole number (``3``, not ``3.0``)."""
    try:
        return int(str(text).strip(), 10)
    except ValueError:
        raise _fail("a whole number", text) from None


def _within(base, ok, rule: str, name: str):
    """A parser: ``base(text)``, then refused unless ``ok(value)`` (``rule`` says what is wanted)."""

    def parse(text):
        v = base(text)
        if not ok(v):
            raise _fail(rule, text)
        return v

    parse.__name__ = name
    return parse


positive = _within(finite, lambda v: v > 0, "a positive number", "positive")
non_negative = _within(finite, lambda v: v >= 0, "zero or a positive number", "non_negative")
fraction = _within(finite, lambda v: 0 < v < 1, "between 0 and 1 (exclusive)", "fraction")
share = _within(finite, lambda v: 0 <= v <= 1, "between 0 and 1", "share")
positive_int = _within(integer, lambda v: v > 0, "a positive whole number", "positive_int")
non_negative_int = _within(integer, lambda v: v >= 0, "zero or a positive whole number", "non_negative_int")
# a simulated field or noise, µT: up to ten times the AK8975's ±1229 µT range (beyond, every reading
# saturates and the numbers stop meaning anything; far beyond, they overflow)
field_scale_ut = _within(finite, lambda v: 0 < v <= 12_290, "a positive number of µT up to 12290", "field_scale_ut")
noise_scale_ut = _within(finite, lambda v: 0 <= v <= 12_290, "from 0 to 12290 µT", "noise_scale_ut")
# what the AK8975 can deliver: a single measurement takes up to 9 ms
rate_hz = _within(integer, lambda v: 1 <= v <= 100, "a rate from 1 to 100 Hz", "rate_hz")


def floats(n: int):
    """A parser for exactly ``n`` comma-separated finite numbers (``1.5,-2,0``) → a tuple."""

    def parse(text) -> tuple:
        parts = str(text).split(",")
        if len(parts) != n:
            raise _fail(f"{n} comma-separated numbers", text)
        try:
            return tuple(finite(p) for p in parts)
        except argparse.ArgumentTypeError:
            raise _fail(f"{n} comma-separated finite numbers", text) from None

    parse.__name__ = f"floats{n}"
    return parse


def names(text) -> tuple:
    """A comma-separated list of names (empty entries dropped; ``''`` is the empty list)."""
    return tuple(c.strip() for c in str(text).split(",") if c.strip())


def existing_file(text) -> str:
    """A file that exists and can be read (``-`` is standard input)."""
    if text == "-":
        return text
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a directory, not a file")
    if not os.path.exists(text):
        raise argparse.ArgumentTypeError(f"no such file: {text!r}")
    if not os.access(text, os.R_OK):
        raise argparse.ArgumentTypeError(f"cannot read {text!r} (permission denied)")
    return text


def output_file(text) -> str:
    """A file that can be created: its folder exists and it is not itself a folder."""
    folder = os.path.dirname(os.path.abspath(text))
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a directory; give a file name")
    if not os.path.isdir(folder):
        raise argparse.ArgumentTypeError(f"the folder of {text!r} does not exist")
    return text


def directory(text) -> str:
    """A folder to write into: it exists, or can be created (its parent exists)."""
    path = os.path.expanduser(text)
    if os.path.exists(path) and not os.path.isdir(path):
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a directory")
    if not os.path.isdir(path) and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
        raise argparse.ArgumentTypeError(f"cannot create {text!r}: its parent folder does not exist")
    return text


# -- the vocabulary ---------------------------------------------------------------------------

PORT_HELP = ("the device: a serial port (/dev/ttyACM0, COM3) or pyserial URL (socket://host:port, "
             "rfc2217://…), sim:// (the simulated board, in real time; sim://?pace=0 as fast as "
             "possible), emu:// (the firmware under simavr), replay://FILE (a capture) or i2c:BUS. "
             "Default: $MAGCAL_PORT, else the config file's port, else the one serial device "
             "plugged in")

VOCABULARY: dict[str, tuple[tuple, dict]] = {
    "port": (("--port",), dict(metavar="URL", help=PORT_HELP)),
    "baud": (("--baud",), dict(type=positive_int, metavar="N",
                               help="serial baud rate (default: the config's baud, 115200)")),
    "dialect": (("--dialect",), dict(choices=("native", "motioncal", "auto"),
                                     help="wire convention: magcal's protocol v1 (native), a PJRC/Adafruit "
                                     "sketch's Raw: lines (motioncal), or detect (auto); default: the "
                                     "config's dialect, native")),
    "config": (("--config",), dict(metavar="FILE", help="YAML settings (every key: magcal config); "
                                   "default: $MAGCAL_CONFIG, else built-in defaults")),
    "json": (("--json",), dict(action="store_true", help="print one JSON object (its \"schema\" key names "
                               "the shape and version) instead of text")),
    "quiet": (("-q", "--quiet"), dict(action="store_true", help="no progress display on stderr (it is "
                                      "also off when stderr is not a terminal)")),
    "rate": (("--rate",), dict(type=rate_hz, metavar="HZ", help="measurement rate, 1…100 Hz (default: "
                               "the config's rate_hz, 50)")),
    "seconds": (("--seconds",), dict(type=positive, metavar="S", help="stop after S seconds")),
    "count": (("--count",), dict(type=positive_int, metavar="N", help="stop after N samples")),
    "timeout": (("--timeout",), dict(type=positive, metavar="S", help="give up after S seconds "
                                     "(default: the config's timeout_s, 120)")),
    "model": (("--model",), dict(choices=("sphere", "ellipsoid", "auto"),
                                 help="sphere (hard iron only), ellipsoid (+ soft iron) or auto (of the models "
                                 "the coverage supports, the one that best predicts held-out time blocks "
                                 "of the recording); default auto")),
    "output": (("-o", "--output"), dict(type=output_file, metavar="FILE", help="the file to write")),
    "state_dir": (("--state-dir",), dict(type=directory, metavar="DIR",
                                         help="the daemon's state directory (state file, status socket, "
                                         "captures); default: the config's daemon.state_dir, "
                                         "else $XDG_STATE_HOME/magcal or ~/.local/state/magcal")),
    "noise_ut": (("--noise-ut",), dict(type=positive, metavar="UT", help="white-noise σ per axis, µT")),
    "mag": (("--mag",), dict(type=integer, metavar="N", help="a flight log's magnetometer, 0-based in the log's "
                             "order (ULog instance; MAG, MAG2, MAG3 …); a log with several and no --mag lists them")),
}

DEVICE_OPTIONS = ("port", "baud", "dialect", "config")


def add(p, *keys: str, **override) -> None:
    """Add the named options of the vocabulary to parser (or group) ``p``. ``override`` may
    sharpen ``help`` or set ``default``/``required`` for one command; type and unit stay."""
    for key in keys:
        flags, kw = VOCABULARY[key]
        kw = dict(kw)
        for k in ("help", "default", "required", "dest"):
            if k in override:
                kw[k] = override[k]
        p.add_argument(*flags, **kw)


def add_alias(p, flag: str, dest: str, **kw) -> None:
    """An old spelling that still works but is not listed (``--samples`` for ``--count``)."""
    p.add_argument(flag, dest=dest, help=argparse.SUPPRESS, **kw)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's help ends with its default (unless the help already says it)."""

    def _get_help_string(self, action):
        h = action.help or ""
        if h is argparse.SUPPRESS or "default" in h or action.default in (None, False, argparse.SUPPRESS):
            return h
        if action.option_strings or action.nargs in ("?", "*"):
            return f"{h} (default: %(default)s)"
        return h


def add_table_options(p) -> None:
    """How to read a recording that is someone else's table (CSV, tab- or space-separated)."""
    g = p.add_argument_group("reading a table", "for CSV or other delimited text that is not magcal's own")
    g.add_argument("--columns", metavar="X,Y,Z", type=names,
                   help="the magnetometer columns: header names or 1-based positions (default: mx,my,mz, "
                   "else mag_x… or magX… style names)")
    g.add_argument("--unit", metavar="UNIT",
                   help="unit of those columns: uT, nT, mG, gauss, tesla, or the µT of one count "
                   "(default: from the column names, else µT)")
    g.add_argument("--time", metavar="COLUMN", help="the time column, name or 1-based position (default: t, time …)")
    g.add_argument("--time-unit", choices=("s", "ms", "us"),
                   help="unit of the time column (default: from its name, else s)")
    g.add_argument("--channels", metavar="A,B,…", type=names,
                   help="keep only these columns as channels (candidate covariates); '' for none "
                   "(default: every other numeric column but a second magnetometer's)")
    g.add_argument("--temp", metavar="COLUMN", help="the die temperature column in °C (read as temp_c; default: "
                   "a column named temp_c)")
    g.add_argument("--current", metavar="COLUMN", help="the interfering current column in A (read as current_a; "
                   "default: a column named current_a)")
    g.add_argument("--delimiter", metavar="C",
                   help="column separator (default: found from the first line; 'tab' or 'space' for those)")


def table_format(args):
    """The TableFormat the table options ask for (all None when none were given)."""
    from ..core.errors import ConfigError, InputError
    from ..recordings.table import TableFormat

    delimiter = {"tab": "\t", "space": " "}.get(args.delimiter, args.delimiter)
    try:
        return TableFormat(columns=args.columns, unit=args.unit, time=args.time, time_unit=args.time_unit,
                           delimiter=delimiter, channels=args.channels, temp=args.temp, current=args.current)
    except InputError as exc:  # the options ask for something invalid: the command line's fault (exit 2)
        raise ConfigError(str(exc)) from None
