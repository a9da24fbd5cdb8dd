"""``magcal status [--state-dir DIR] [--json]``: what a daemon is doing (or last did).

Asks the running daemon over its local UNIX socket; when nobody answers, reads the state file
(the newest valid one) and says how old it is. Exit status: 0 when the daemon is running; 1
when it is not (the report is still printed, from the state file, or saying that no daemon has
run with this state directory); 6 when the state file is unreadable. ``--json`` prints
``magcal.status/1`` in every case, with ``running`` and ``source`` (socket, state file, none)."""

from __future__ import annotations

import math
import os
import time

from ..core.errors import StateError
from ..recordings.state import state_directory
from .common import document, load_settings, print_json
from .exits import Exit
from .options import add

HELP = "report a daemon's live state: samples, coverage, last calibration, faults"


def add_arguments(p) -> None:
    add(p, "state_dir", "config", "json")


def _pid_alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except (OSError, TypeError, ValueError):
        return False
    return True


def gather(state_dir) -> tuple[dict, str]:
    """(status, source) — source is ``socket``, ``state file`` or ``none`` (no daemon has run
    with this state directory)."""
    from ..app.daemon import query_socket
    from ..recordings.state import StateFiles

    live = query_socket(state_dir)
    if live is not None:
        return live, "socket"
    store = StateFiles(state_dir)
    data = store.load()
    if data is None:
        return {"running": False, "state_dir": str(store.directory),
                "note": f"no daemon state in {store.directory}: no `magcal run` has used this state "
                "directory (give --state-dir DIR, or state_dir: in the config file)"}, "none"
    saved = data.get("saved_utc")
    if not isinstance(data.get("status"), dict) or isinstance(saved, bool) or not isinstance(saved, (int, float)) \
            or not math.isfinite(saved):
        raise StateError(f"{store.current}: holds no daemon status this magcal can show (its checksum holds, but "
                         "it was not written by `magcal run`)")
    status = dict(data["status"])
    status["saved_utc"] = saved
    status["age_s"] = round(time.time() - float(saved), 1)
    status["generation"] = data.get("generation")
    if status.get("running") and not _pid_alive(status.get("pid")):
        status["running"] = False
        status["note"] = "the daemon is not running (it stopped without writing a final state)"
    return status, "state file"


def run(args) -> int:
    state_dir = state_directory(args.state_dir or load_settings(args).daemon.state_dir, create=False)
    status, source = gather(state_dir)
    status["source"] = source
    if args.json:
        print_json(document("status", status))
    elif source == "none":
        print(f"daemon     not running; {status['note']}")
    else:
        import contextlib
        import io

        text = io.StringIO()
        try:
            with contextlib.redirect_stdout(text):
                _print_text(status)
        except (TypeError, ValueError, KeyError, IndexError, AttributeError):
            raise StateError(f"{state_dir}: the daemon status it holds is malformed (`magcal status --json` "
                             "shows it as stored)") from None
        print(text.getvalue(), end="")
    return Exit.OK if status.get("running") else Exit.NO


def _print_text(s: dict) -> None:
    state = "running" if s.get("running") else "not running"
    age = f", state saved {s['age_s']:.0f} s ago" if s.get("age_s") is not None else ""
    print(f"daemon     {state} (from the {s['source']}{age}), pid {s.get('pid')}, port {s.get('port')}")
    print(f"link       {'connected' if s.get('connected') else 'disconnected'}, epoch {s.get('epoch')}, "
          f"last seq {s.get('last_seq')}")
    print(f"samples    {s.get('samples')} collected ({s.get('samples_in')} received), "
          f"coverage {100 * (s.get('coverage') or 0):.0f}%")
    cal = s.get("calibration")
    if cal:
        o = cal["offset_ut"]
        print(f"stored     offset [{o[0]:.2f}, {o[1]:.2f}, {o[2]:.2f}] µT, field {cal['field_ut']:.2f} µT")
    else:
        print("stored     no calibration on the device")
    last = s.get("last_calibration")
    if last:
        when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(last["written_utc"]))
        print(f"written    {when}, verified by read-back, rms {last['rms_ut']:.3f} µT "
              f"({s.get('recalibrations')} recalibration(s) by this daemon)")
    mon = s.get("monitor")
    if mon:
        last_v = mon.get("last") or {}
        p = last_v.get("p_value")
        print(f"monitor    {mon['phase']}, {mon['windows']} windows, {mon['alarms']} alarm(s)"
              + (f", last p = {p:.3g}" if p is not None else ""))
    faults = s.get("faults") or {}
    print("faults     " + (", ".join(f"{k} {v}" for k, v in faults.items()) or "none"))
    if s.get("note"):
        print(f"note       {s['note']}")
