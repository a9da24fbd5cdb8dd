"""``magcal ARGV`` as real processes that a test may kill -9, without paying Python's start-up
and magcal's imports (numpy, scipy …) for each one.

``Launcher`` starts one interpreter that imports ``magcal.cli`` once, then runs ``preamble``
(code of the test's: the modules its command imports, so they too are imported once; a patch,
e.g. to count what the simulated board stores) and then forks one child per
``start``: the child runs the same ``main(argv)`` as ``python -m magcal`` in a process of its
own — its own pid, stdin on /dev/null, stdout and stderr to files, its own signal handlers,
state directory, locks and ledger — and ends with main's exit status. ``os.kill(pid, SIGKILL)``
kills it as it kills any process. What a child no longer pays is exactly the interpreter's
start-up and the imports, which precede everything a command does; ``startup_s`` says how long
they took here (spawn to imports done), so a test that kills "t seconds after the start" can
kill at the same moment of the command's life.

The launcher is single-threaded, so forking it is safe; it reaps its children when asked
(``poll``, ``wait``); closing it kills those still running."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time

_SERVER = r"""
import json, os, sys, traceback
from magcal.cli import main  # first: it keeps BLAS to one thread before numpy is imported
exec(sys.argv[1])


def _child(req):
    code = 1
    try:
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, 0)
        for fd, path in ((1, req["stdout"]), (2, req["stderr"])):
            os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644) if path else null, fd)
        sys.argv = ["-c", *req["argv"]]
        code = main(req["argv"])
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        traceback.print_exc()
    finally:
        for f in (sys.stdout, sys.stderr):
            try:
                f.flush()
            except Exception:
                pass
        os._exit(code if isinstance(code, int) else 1)


def _answer(obj):
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


_answer({"ready": True})
for line in sys.stdin:
    req = json.loads(line)
    if "argv" in req:
        pid = os.fork()
        if pid == 0:
            _child(req)
        _answer({"pid": pid})
    else:
        pid, status = os.waitpid(req["pid"], 0 if req["block"] else os.WNOHANG)
        _answer({"status": os.waitstatus_to_exitcode(status) if pid else None})
"""


class Launcher:
    """One interpreter with magcal imported, forking a ``magcal`` process per ``start``."""

    def __init__(self, preamble: str = "", env: dict | None = None, timeout_s: float = 120.0):
        t0 = time.monotonic()
        self._proc = subprocess.Popen([sys.executable, "-c", _SERVER, preamble], env=env, text=True,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self._live: set[int] = set()  # children started and not yet reaped
        self._ask(None, timeout_s)
        self.startup_s = time.monotonic() - t0  # what each `python -m magcal` pays before main()

    def _ask(self, request: dict | None, timeout_s: float) -> dict:
        if request is not None:
            self._proc.stdin.write(json.dumps(request) + "\n")
            self._proc.stdin.flush()
        ready, _, _ = select.select([self._proc.stdout], [], [], timeout_s)
        line = self._proc.stdout.readline() if ready else ""
        if not line:
            raise RuntimeError(f"the magcal launcher did not answer {request} within {timeout_s} s "
                               f"(exit status {self._proc.poll()})")
        return json.loads(line)

    def start(self, argv, stdout=None, stderr=None) -> int:
        """Fork ``magcal ARGV``; its pid. ``stdout``/``stderr``: file paths (None: /dev/null)."""
        req = {"argv": [str(a) for a in argv], "stdout": stdout and str(stdout), "stderr": stderr and str(stderr)}
        pid = self._ask(req, 30.0)["pid"]
        self._live.add(pid)
        return pid

    def poll(self, pid: int) -> int | None:
        """The exit status of a child that ended (negative: the signal that killed it), else None."""
        return self._reaped(pid, self._ask({"pid": pid, "block": False}, 30.0)["status"])

    def wait(self, pid: int, timeout_s: float = 60.0) -> int:
        """Wait for the child to end; its exit status (negative: the signal that killed it)."""
        return self._reaped(pid, self._ask({"pid": pid, "block": True}, timeout_s)["status"])

    def _reaped(self, pid: int, status: int | None) -> int | None:
        if status is not None:
            self._live.discard(pid)
        return status

    def close(self) -> None:
        """Kill what is still running (a test that failed half-way leaves no daemon behind)."""
        for pid in self._live:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self._proc.stdin.close()
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()

    def __enter__(self) -> "Launcher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
