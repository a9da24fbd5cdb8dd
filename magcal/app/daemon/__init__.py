"""``magcal run``: the long-running service that keeps one device calibrated.

The only loop in magcal with side effects, and a small one: each turn it reads the device and
hands what came to its collaborators, each a small object of its own module, testable alone:

    supervisor.LinkSupervisor   connect (open, identify, read the stored calibration, start),
                                back-off, stall, reset, drain — owns the device
    intake.Intake               each sample line once, in order, counted (epochs, duplicates,
                                a resumed replay's lines skipped)
    drift.DriftWatcher          the calibration held and the monitor that tests it still fits
    recalibrator.Recalibrator   when to write: collect, gates, solve (a decider)
    recalibrator.CalibrationWriter   write, verify by read-back, remember what was verified
    persistence.StateKeeper     the state file a restart resumes from; the state-dir lock
    ledger.WriteLedger          every EEPROM write recorded (fsynced) before it is sent: the
                                write budget is charged from it, so it survives kill -9
    control.ControlSocket       ``status.sock``: the live status for ``magcal status``
    recorder.RollingCapture     the bounded capture of every byte read
    journal.Journal             every decision, typed (``Decision``), logged once

    ┌──────────── connect ◀─── back-off ◀──────────────────────────────────────────────────┐
    │                                                                                      │
    └▶ read ─▶ intake ─▶ session (collect) ─▶ drift watcher ─▶ (deciders: solve, gates,    │
          │                                                   writer: write, read back)   │
          └─ port lost / stalled / replay ended ─────────────────────────────────────────┘

Faults it survives: the port vanishing (USB unplug: ``PortUnavailable``) or going silent
(``daemon.stall_s``), device resets (streaming is restarted), garbage and torn lines (the
framer counts them), a device that stops acknowledging (a write fails, streaming goes on), a
write echoed wrongly (not verified ⇒ not reported; the previous calibration is put back), a
full disk for captures or state (counted, logged, the data keeps flowing).

State survives a crash: every ``daemon.state_every_s`` the accumulated session, the monitor and
the counters are written (``persistence``); a restart resumes from them (on a ``replay://``
source, after the lines the saved session already holds). SIGTERM/SIGINT stop cleanly (state
written); SIGHUP reloads the config file, keeping the old settings when the new ones are
invalid. ``status.sock`` in the state directory answers ``magcal status``; there is no network
listener.
"""

from .control import query_socket
from .journal import Decision

__all__ = ["Collaborators", "Daemon", "Decision", "Stop", "query_socket"]


def __getattr__(name: str):
    """``Daemon``, ``Collaborators`` and ``Stop`` are imported on first use: the daemon's parts
    import the tracker and the monitor (scipy.stats), which ``magcal status`` — asking the
    socket or reading the state file — has no use for."""
    if name in ("Collaborators", "Daemon", "Stop"):
        from . import daemon

        return getattr(daemon, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
