"""``magcal run [--port URL] [--config FILE] [--state-dir DIR]``: the daemon (see magcal.app.daemon).

Runs until SIGTERM or Ctrl-C (exit 0, state written); SIGHUP reloads ``--config``. Logs every
decision to stderr (one line each; under systemd they land in the journal). ``--samples N``
stops after N collected samples (for tests and the soak benchmark)."""

from __future__ import annotations

import logging
import sys

from ..app.daemon import Daemon
from .common import add_config_option, add_port_options, load_settings

HELP = "keep a device calibrated: stream, reconnect, monitor drift, recalibrate when allowed"


def add_arguments(p) -> None:
    add_port_options(p)
    add_config_option(p)
    p.add_argument("--state-dir", metavar="DIR", help="state file, status socket and captures "
                   "(default from config: ~/.local/state/magcal)")
    p.add_argument("--rate", type=int, metavar="HZ", help="measurement rate, 1…100 Hz")
    p.add_argument("--recalibrate", action="store_true", default=None,
                   help="collect, refit and write back when the calibration no longer fits (daemon.recalibrate)")
    p.add_argument("--samples", type=int, metavar="N", help="stop after N collected samples")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def run(args) -> int:
    overrides = {"rate_hz": args.rate}
    daemon_over = {}
    if args.state_dir:
        daemon_over["state_dir"] = args.state_dir
    if args.recalibrate:
        daemon_over["recalibrate"] = True
    if daemon_over:
        overrides["daemon"] = daemon_over
    settings = load_settings(args, **overrides)
    logging.basicConfig(
        stream=sys.stderr,
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    cli_overrides = {k: v for k, v in {
        "port": args.port, "baud": args.baud, "dialect": args.dialect, **overrides,
    }.items() if v is not None}
    daemon = Daemon(settings, config_path=args.config, overrides=cli_overrides, max_samples=args.samples)
    return daemon.run()
