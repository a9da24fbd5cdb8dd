"""``magcal run [--port URL] [--config FILE] [--state-dir DIR]``: the daemon (see magcal.app.daemon).

Runs until SIGTERM or Ctrl-C (exit 0, state written); SIGHUP reloads ``--config``. Logs every
decision to stderr, one line each. At a terminal or in a file each line starts with the time;
under systemd (``$JOURNAL_STREAM`` names stderr) the journal adds the time itself, so the line
carries the level as a syslog priority prefix instead (``<4>`` for a warning) and no timestamp.
``--count N`` stops after N collected samples (for tests and the soak benchmark)."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading

from ..recordings.state import state_directory
from .common import device_settings
from .options import add, add_alias, positive_int

HELP = "keep a device calibrated: stream, reconnect, monitor drift, recalibrate when allowed"

PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}


def add_arguments(p) -> None:
    add(p, "port", "baud", "dialect", "config", "state_dir", "rate")
    p.add_argument("--recalibrate", action="store_true", default=None,
                   help="write calibrations to the device (daemon.recalibrate): the tracker's when significantly "
                        "better (daemon.keep: tracker), or a refit after the drift monitor rings (keep: alarm)")
    add(p, "count", help="stop after N collected samples (default: run until stopped)")
    add_alias(p, "--samples", dest="count", type=positive_int)
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="the least important decisions logged")
    from .view import add_view_option

    add_view_option(p)


def to_journal(stream=None, environ=None) -> bool:
    """True when ``stream`` (stderr) is connected to the systemd journal (``$JOURNAL_STREAM``
    holds its device and inode)."""
    stream = stream or sys.stderr
    environ = os.environ if environ is None else environ
    dev_ino = environ.get("JOURNAL_STREAM", "")
    try:
        st = os.fstat(stream.fileno())
        dev, ino = (int(x) for x in dev_ino.split(":"))
    except (ValueError, OSError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


class JournalFormatter(logging.Formatter):
    """``<priority>name: message`` — the journal keeps the time and reads the level."""

    def format(self, record: logging.LogRecord) -> str:
        return f"<{PRIORITY.get(record.levelno, 6)}>{record.name}: {record.getMessage()}"


def log_handler(stream=None, environ=None) -> logging.Handler:
    handler = logging.StreamHandler(stream or sys.stderr)
    if to_journal(stream, environ):
        handler.setFormatter(JournalFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    return handler


class EarlyHangup:
    """SIGHUP taken from the moment ``run`` starts — not only once the daemon's own handlers are
    in (its default action would kill the service in its first seconds): a hangup before then
    is remembered and handed to the daemon as a reload."""

    def __init__(self):
        self.pending = False
        self._target = None
        self._previous = None
        if hasattr(signal, "SIGHUP") and threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGHUP, self._hangup)

    def _hangup(self, *_):
        if self._target is None:
            self.pending = True
        else:
            self._target()

    def hand_to(self, reload) -> None:
        """From now on a hangup is ``reload()``; one that came before is handed over now."""
        self._target = reload
        if self.pending:
            reload()

    def restore(self) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGHUP, self._previous)


def run(args) -> int:
    hangup = EarlyHangup()
    try:
        return _run(args, hangup)
    finally:
        hangup.restore()


def _run(args, hangup: EarlyHangup) -> int:
    from ..app.daemon import Collaborators, Daemon

    overrides = {"rate_hz": args.rate}
    daemon_over = {}
    if args.state_dir:
        daemon_over["state_dir"] = args.state_dir
    if args.recalibrate:
        daemon_over["recalibrate"] = True
    if daemon_over:
        overrides["daemon"] = daemon_over
    settings = device_settings(args, **overrides)
    state_directory(settings.daemon.state_dir)  # a file, or a directory it cannot write: said now
    logging.basicConfig(level=getattr(logging, args.log_level), handlers=[log_handler()])
    cli_overrides = {k: v for k, v in {
        "port": settings.port, "baud": args.baud, "dialect": args.dialect, **overrides,
    }.items() if v is not None}
    view = _view(args)
    collaborators = Collaborators(on_sample=view.on_sample) if view else Collaborators()
    daemon = Daemon(settings, config_path=args.config, overrides=cli_overrides, max_samples=args.count,
                    collaborators=collaborators)
    hangup.hand_to(daemon.request_reload)
    if view is None:
        return daemon.run()
    view.daemon = daemon
    try:
        return daemon.run()
    finally:
        view.close()


def _view(args):
    """``--view``: the daemon's collecting and what it wrote, live in the browser (``magcal.cli.view``)."""
    if not args.view:
        return None
    from .view import DaemonView, start

    return DaemonView(start(json_output=False))
