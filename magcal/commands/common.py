"""Options and output helpers shared by the subcommands."""

from __future__ import annotations

import json
import sys

from .. import config


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
