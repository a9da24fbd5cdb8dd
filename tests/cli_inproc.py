"""``magcal ARGV`` run in this process: its exit status and what it printed, in the shape
``subprocess.run`` gives them (``returncode``, ``stdout``, ``stderr``), for tests that check a
command's output and status. It is the same ``main(argv)`` that ``python -m magcal`` runs,
without a new interpreter importing numpy, scipy and matplotlib again for each command; an
exception the command does not turn into a status fails the test where a subprocess would
have printed a traceback. Tests of the process itself (its entry point, signals, a second run
in a fresh interpreter) start a subprocess instead."""

from __future__ import annotations

import contextlib
import io
import subprocess


def run_magcal(*argv) -> subprocess.CompletedProcess:
    from magcal.cli import main

    args = [str(a) for a in argv]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(args)
        except SystemExit as exc:  # argparse's usage errors exit as the command line would
            code = 0 if exc.code is None else exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess(["magcal", *args], code, out.getvalue(), err.getvalue())
