"""What the daemon decided, as typed values: every decision is a ``Decision``, logged once (logger
``magcal.daemon``) and kept in a bounded journal that the status and the state file show.

An entry is a plain dict for JSON: ``{"t_utc", "what" (the sentence), "decision" (its code),
"at_sample", …details}``. Code that acts on decisions, and tests, compare ``Decision`` values,
never the sentence.
"""

from __future__ import annotations

import logging
from collections import deque
from enum import Enum
from typing import Callable

import numpy as np

log = logging.getLogger("magcal.daemon")

DECISIONS_KEPT = 50


# every decision the daemon takes: its code, the log level, the sentence logged
DECISIONS = """
started               info     daemon started
stopped               info     daemon stopped
source_ended          info     source ended: stopping
connect_failed        warning  connect failed; retrying
connected             info     connected
disconnected          info     disconnected
link_lost             warning  disconnected
device_reset          warning  device reset itself; restarting the stream
stored_unreadable     warning  could not read the stored calibration
stored_unusable       warning  the device's stored record cannot be used; taken as none
nothing_stored        warning  device holds no calibration; monitoring stops
calibration_loaded    info     device calibration loaded; monitor learns the noise
monitor_restarted     info     monitor restarted; monitor learns the noise
new_calibration       info     new calibration; monitor learns the noise
monitor_retuned       info     monitor settings changed; monitor learns the noise
baseline_done         info     monitor baseline done
drifted               warning  calibration no longer fits the data
collecting            info     collecting for a recalibration
tracker_restarted     info     the tracker starts afresh on the new field; it writes once the gates pass
reporting_only        info     recalibration disabled (daemon.recalibrate: false); reporting only
solving               info     gates pass on the live estimate: solving
refused               warning  recalibration refused
written               info     calibration written and verified by read-back
keeping               info     the tracker's calibration is better than the device's: writing
not_written           error    calibration NOT written
budget_wait           info     EEPROM write budget spent for now; not written
write_interrupted     warning  a write was interrupted (the process was killed); counted as spent
ledger_unavailable    error    the write ledger cannot be opened; nothing will be written
record_unreadable     warning  could not re-read the device's calibration
record_unverified     error    the device holds a record this daemon did not verify; monitoring the verified one
reloaded              info     config reloaded
reload_rejected       error    config reload rejected; keeping the old settings
state_not_written     error    state not written
no_state              info     no previous state; starting fresh
state_refused         error    state refused; starting fresh
state_unusable        error    state unusable; starting fresh
state_other_port      warning  state was written for another port; keeping its counters only
resumed               info     resumed
replay_skips          info     replay resumes after the lines already taken
capture_rolling       info     rolling capture
capture_not_started   error    capture not started; streaming without it
capture_stopped       error    capture stopped; streaming continues
socket_unavailable    warning  status socket unavailable; the state file still answers
"""
_ROWS = [line.split(None, 2) for line in DECISIONS.strip().splitlines()]

Decision = Enum("Decision", [(code.upper(), code) for code, _, _ in _ROWS], module=__name__)
Decision.__doc__ = """A decision, as a typed value: ``Decision.CONNECTED``; ``.value`` its code, ``.text`` the
sentence logged, ``.level`` the log level (the table ``DECISIONS``)."""
for _code, _level, _text in _ROWS:
    Decision(_code).text = _text
    Decision(_code).level = getattr(logging, _level.upper())


class Journal:
    """The decisions taken, newest last (at most ``keep``); ``position()`` says at which sample."""

    def __init__(self, wall: Callable[[], float], position: Callable[[], int], keep: int = DECISIONS_KEPT):
        self._wall = wall
        self._position = position
        self.entries: deque[dict] = deque(maxlen=keep)

    def record(self, decision: Decision, **detail) -> dict:
        detail = {k: plain(v) for k, v in detail.items() if v is not None}
        at = self._position()
        entry = {"t_utc": round(self._wall(), 3), "what": decision.text, "decision": decision.value, "at_sample": at}
        entry.update(detail)
        self.entries.append(entry)
        log.log(decision.level, "%s%s (at sample %d)", decision.text,
                "".join(f" {k}={v}" for k, v in detail.items()), at)
        return entry

    def decisions(self) -> list[Decision]:
        """The decisions kept, in order (entries of an older state without a code are left out)."""
        codes = {d.value: d for d in Decision}
        return [codes[e["decision"]] for e in self.entries if e.get("decision") in codes]

    def find(self, decision: Decision) -> list[dict]:
        """The entries of one decision, in order."""
        return [e for e in self.entries if e.get("decision") == decision.value]

    def recent(self, n: int = 10) -> list[dict]:
        return list(self.entries)[-n:]

    def restore(self, entries) -> None:
        """Put back the entries of a resumed state, before anything new."""
        self.entries.extend(e for e in entries if isinstance(e, dict))


def plain(v):
    """numpy scalars and arrays → Python numbers and lists (for logs and JSON)."""
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (list, tuple, np.ndarray)):
        return [plain(x) for x in v]
    return v
