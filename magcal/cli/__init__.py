"""The ``magcal`` command line: ``main(argv=None)``.

Each subcommand lives in ``magcal/cli/<name>.py`` with ``add_arguments(parser)`` and
``run(args) -> int`` (the exit status, ``magcal.cli.exits``); its one line of help is in
``COMMANDS`` below. Only the module of the command being run is imported, so ``magcal --help``
and a small ``fit`` start quickly (``bench/startup.py``). This file wires the commands together
and turns magcal's own errors into a one-line message and their exit status.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# One BLAS thread: magcal's solves are small (tens of unknowns), and a threaded BLAS waits on its
# threads far longer than it computes — many times over on a busy machine. This must run before
# numpy is first imported; a caller's own setting wins.
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

from .. import __version__
from .exits import Exit, code_for, epilog

COMMANDS = {
    "calibrate": "calibrate a device end to end and write the result back (verified by read-back)",
    "fit": "fit a sphere or ellipsoid calibration to recordings (captures, logs, tables)",
    "track": "replay a recording through the tracker: the calibration in force at every sample",
    "diagnose": "find what a sphere calibration leaves out of a recording, model it, show held-out gain",
    "record": "record the raw bytes from a device (with receive times) as a capture file",
    "export": "export a recording as CSV (t, mx, my, mz in µT, temp_c, other channels)",
    "write": "write a calibration from fit/diagnose JSON to a device (verified by read-back)",
    "show": "print the calibration stored for a device (and run its self-test)",
    "stream": "print live samples (µT), optionally calibrated with the stored calibration",
    "run": "keep a device calibrated: stream, reconnect, monitor drift, recalibrate when allowed",
    "status": "report a daemon's live state: samples, coverage, last calibration, faults",
    "simulate": "write a simulated MPU-9150 recording (CSV, µT) with known physics",
    "fleet": "analyse every log of a fleet (pool or Dask cluster): each compass's history and where it changed",
    "config": "print the configuration template: every setting, its default and meaning (for --config)",
    "service": "install the systemd unit (magcal@PORT.service), its config file and docs",
    "firmware": "build the Arduino firmware from the packaged sources, or flash it to a board",
}

DESCRIPTION = "Calibrate the MPU-9150's magnetometer: stream, fit, diagnose, write back, verify."


def _load(name: str):
    return importlib.import_module(f"magcal.cli.{name}")


def _wanted(argv) -> str | None:
    """The command named on the command line (the first word that is not an option)."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported and its options added ("all": every
    command's, for tests that look at the whole surface)."""
    from .options import HelpFormatter

    parser = argparse.ArgumentParser(prog="magcal", description=DESCRIPTION, epilog=epilog(),
                                     formatter_class=HelpFormatter)
    parser.add_argument("--version", action="version", version=f"magcal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_ in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_, epilog=epilog(), formatter_class=HelpFormatter)
        if command in (name, "all"):
            mod = _load(name)
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
    return parser


def _one_blas_thread() -> None:
    """magcal's matrices are n×3 and at most 10×10: BLAS threads only contend for the cores
    (a 300 000-sample fit took 5× the CPU with them). Set before numpy is first imported;
    a user's own setting wins."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def main(argv=None) -> int:
    _one_blas_thread()
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_wanted(argv))
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return int(Exit.USAGE)
    return int(_run(args))


def _run(args) -> int:
    from ..core.errors import MagcalError

    try:
        return int(args._run(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: {exc}", file=sys.stderr)
        return code_for(exc)
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return Exit.INTERRUPTED
    except BrokenPipeError:  # the reader went away (`magcal fit x --json | head`): not an error of ours
        try:
            sys.stdout = open(os.devnull, "w")  # nothing more can be written; keep exit quiet
        except OSError:
            pass
        return Exit.PIPE


if __name__ == "__main__":
    sys.exit(main())
