"""The ``magcal`` command line: ``main(argv=None)``.

Each subcommand lives in ``magcal/cli/<name>.py`` with ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int`` (the exit code). This file only wires
them together and turns magcal's own errors into a one-line message and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from .. import __version__
from ..core.errors import MagcalError

COMMANDS = (
    "calibrate",
    "fit",
    "diagnose",
    "record",
    "export",
    "write",
    "show",
    "stream",
    "run",
    "status",
    "simulate",
)


def _load(name: str):
    return importlib.import_module(f"magcal.cli.{name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magcal",
        description="Calibrate the MPU-9150's magnetometer: stream, fit, diagnose, write back, verify.",
    )
    parser.add_argument("--version", action="version", version=f"magcal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = _load(name)
        except ModuleNotFoundError as exc:
            if exc.name == f"magcal.cli.{name}":
                continue  # not part of this build
            raise
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (`magcal fit x --json | head`): not an error of ours
        try:
            sys.stdout = open(os.devnull, "w")  # nothing more can be written; keep exit quiet
        except OSError:
            pass
        return 141


if __name__ == "__main__":
    sys.exit(main())
