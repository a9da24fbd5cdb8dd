"""The daemon itself: one device kept calibrated by a loop that reads it and hands what came
to its parts (the package docstring, ``magcal.app.daemon``, draws the loop and its faults).

What the daemon calls beyond its own parts — the device opener and its options, the two
clocks, sleep, a listener for each sample collected — comes as one value (``Collaborators``);
its parts are built from the settings, the state directory and those (``Parts.build``).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Callable

import numpy as np

from ...core.errors import ConfigError
from ...core.events import Event
from ...core.sample import Sample
from ...devices import open_device as _open_device
from ...devices.base import Device
from ...devices.port import scheme_of
from ...logic.session import Session
from ...recordings.state import user_state_dir
from .. import config
from .control import ControlSocket
from .drift import DriftWatcher
from .intake import Intake, Take
from .journal import Decision, Journal
from .ledger import WriteLedger
from .persistence import STATE_KIND, Saved, StateDirLock, StateKeeper, why_unusable
from .recalibrator import CalibrationWriter, Recalibrator
from .recorder import RollingCapture
from .supervisor import LinkSupervisor
from .tracking import TrackingDecider

READ_S = 0.1  # one read's wait
BATCH_S = 0.1  # a read that brought only a trickle waits out this much, so lines are taken in
BATCH_MIN = 16  # batches rather than one wake-up per line (100 Hz ⇒ ~10 wake-ups a second;
# measured with bench/daemon_soak.py --realtime 40: 1.7 % of one core at 0.1 s, 2.3 % at 0.05 s)


class Stop(Enum):
    """Why the loop ended."""

    REQUESTED = "requested"  # request_stop(), SIGTERM, SIGINT
    FAILED = "an error it cannot go on from"  # e.g. a port string no backend takes
    SOURCE_ENDED = "the recording ended"
    ENOUGH_SAMPLES = "collected the samples asked for"


@dataclass(frozen=True)
class Collaborators:
    """What the daemon calls beyond its own parts: ``open_device(url, **device_options)``, the
    monotonic ``clock`` and the ``wall`` clock (seconds), ``sleep``, and ``on_sample(epoch,
    sample)`` for each sample collected (None: nobody listens)."""

    open_device: Callable[..., Device] = _open_device
    device_options: dict | None = None
    clock: Callable[[], float] = time.monotonic
    wall: Callable[[], float] = time.time
    sleep: Callable[[float], None] = time.sleep
    on_sample: Callable[[int, Sample], None] | None = None


@dataclass(frozen=True)
class Parts:
    """The daemon's parts, each a small object of its own module (the package docstring says
    what each does), sharing one fault counter and one journal."""

    faults: Counter
    intake: Intake
    journal: Journal
    capture: RollingCapture
    link: LinkSupervisor
    drift: DriftWatcher
    recalibrator: Recalibrator
    writer: CalibrationWriter
    tracking: TrackingDecider
    keeper: StateKeeper
    control: ControlSocket

    @classmethod
    def build(cls, settings: config.Settings, state_dir: Path, c: Collaborators) -> "Parts":
        faults: Counter = Counter()
        intake = Intake()
        journal = Journal(c.wall, position=lambda: intake.samples)
        capture = RollingCapture(state_dir, journal, faults)
        link = LinkSupervisor(settings, journal, faults, open_device=c.open_device, options=c.device_options,
                              tap=lambda: capture.writer, on_capture_error=capture.failed, clock=c.clock)
        # the deciders (``daemon.keep``, ``Daemon._decide``): the tracker keeps the device calibrated
        # all along; the recalibrator writes a refit after the calibration held stopped fitting.
        return cls(faults=faults, intake=intake, journal=journal, capture=capture, link=link,
                   drift=DriftWatcher(settings.daemon, journal, faults),
                   recalibrator=Recalibrator(settings, journal, faults),
                   writer=CalibrationWriter(journal, faults, c.wall),
                   tracking=TrackingDecider(settings, journal, faults, c.wall, WriteLedger(state_dir, c.wall)),
                   keeper=StateKeeper(state_dir, journal, faults, c.clock),
                   control=ControlSocket(state_dir, journal))


class Daemon:
    """One device, kept calibrated. ``run()`` blocks until ``request_stop()`` (or SIGTERM)."""

    def __init__(
        self,
        settings: config.Settings,
        *,
        state_dir: str | os.PathLike | None = None,
        config_path: str | None = None,
        overrides: dict | None = None,
        max_samples: int | None = None,
        collaborators: Collaborators = Collaborators(),
    ):
        self.settings = settings
        self.config_path = config_path
        self.overrides = dict(overrides or {})
        self.state_dir = Path(state_dir or settings.daemon.state_dir or user_state_dir()).expanduser()
        c = collaborators
        self._clock, self._wall, self._sleep = c.clock, c.wall, c.sleep
        self.on_sample = c.on_sample
        self.max_samples = max_samples
        parts = Parts.build(settings, self.state_dir, c)
        self.faults, self.intake, self.journal, self.capture = parts.faults, parts.intake, parts.journal, parts.capture
        self.link, self.drift, self.keeper, self.control = parts.link, parts.drift, parts.keeper, parts.control
        self.recalibrator, self.writer, self.tracking = parts.recalibrator, parts.writer, parts.tracking
        self.started_wall = c.wall()
        self.stopped_by: Stop | None = None
        self._stop, self._reload = threading.Event(), threading.Event()

    def request_stop(self) -> None:
        self._stop.set()

    def request_reload(self) -> None:
        self._reload.set()

    # -- the loop -----------------------------------------------------------------------------------
    def run(self) -> int:
        with StateDirLock(self.state_dir):
            self.resume()
            self.tracking.open_ledger()  # the budget as spent by every write, from before the first save
            if self.settings.daemon.socket:
                self.control.open()
            self.capture.open(self.settings)
            self.journal.record(Decision.STARTED, port=self.settings.port, state_dir=str(self.state_dir),
                                pid=os.getpid())
            previous = _install_signals(self.request_stop, self.request_reload)
            try:
                self._loop()
            except BaseException:
                self.stopped_by = self.stopped_by or Stop.FAILED
                raise
            finally:
                self._shut_down()
                _restore_signals(previous)
        return 0

    def _loop(self) -> None:
        while not self._stop.is_set():
            if self._reload.is_set():
                self._reload.clear()
                self.reload()
            if not self.link.connected and not self._connect():
                if self.keeper.due(self._clock()):
                    self.save()  # the status file shows the outage too
                self._wait(self.link.backoff_s())
                continue
            self.step()

    def _shut_down(self) -> None:
        self.link.drain(self.handle)
        self.link.close()
        self.journal.record(Decision.STOPPED, reason=(self.stopped_by or Stop.REQUESTED).value)
        self.save(final=True)
        self.capture.close()
        self.control.close()
        self.tracking.close_ledger()

    def step(self) -> None:
        """One read and everything it leads to."""
        t_read = self._clock()
        items = self.link.read(READ_S)
        if self.link.ended:
            self.journal.record(Decision.SOURCE_ENDED, port=self.settings.port)
            self._finish(Stop.SOURCE_ENDED)
            return
        if items:
            self.handle(items)
        now = self._clock()
        if not self.link.connected or self.link.stalled(now):
            return
        self._decide()
        self.control.serve(self.status)
        if self.keeper.due(now):
            self.save()
        if self.max_samples is not None and self.intake.samples >= self.max_samples:
            self._finish(Stop.ENOUGH_SAMPLES)
        if 0 < len(items) < BATCH_MIN and not self._stop.is_set():
            rest = BATCH_S - (self._clock() - t_read)
            if rest > 0:
                self._sleep(rest)

    def _finish(self, why: Stop) -> None:
        self.stopped_by = why
        self._stop.set()

    def _wait(self, seconds: float) -> None:
        end = self._clock() + seconds
        while not self._stop.is_set():
            left = end - self._clock()
            if left <= 0:
                break
            self.control.serve(self.status)
            if self._reload.is_set():
                break
            self._sleep(min(0.05, left))

    def _connect(self) -> bool:
        conn = self.link.connect()
        if conn is None:
            return False
        self.intake.new_epoch()
        stored = conn.stored if conn.knows_record else self.drift.calibration  # a replay: keep what the state knew
        self.journal.record(Decision.CONNECTED, port=self.settings.port, firmware=conn.identity.firmware or None,
                            epoch=self.intake.epoch, stored_calibration="yes" if stored else "none")
        self.drift.adopt(stored, self.link.matches)
        return True

    # -- data -----------------------------------------------------------------------------------------
    def handle(self, items) -> None:
        fields, temps, heard = [], [], False
        for item in self.intake.admit(items, replay=scheme_of(self.settings.port) == "replay"):
            if isinstance(item, Event):
                self._event(item)
                self.recalibrator.take(item)
            elif isinstance(item, Sample):
                heard = True
                take = self.intake.take(item)
                if take is Take.DUPLICATE:
                    self.faults["duplicate_lines"] += 1
                    continue
                self.recalibrator.take(item, collected=take is Take.GOOD)
                if take is Take.GOOD:
                    self.tracking.take(item.field_ut, item.t_s)
                    fields.append(item.field_ut)
                    temps.append(np.nan if item.temp_c is None else item.temp_c)
                    if self.on_sample is not None:
                        self.on_sample(self.intake.epoch, item)
        if heard:
            self.link.heard()
        if fields and self.drift.add(fields, temps):  # what was collected belongs to the old field
            tracker_keeps = self.settings.daemon.keep is config.Keep.TRACKER  # then it says what happens next
            self.recalibrator.drifted(self._may_write(), say=not tracker_keeps)
            self.tracking.restart(self._may_write() if tracker_keeps else None)

    def _event(self, ev: Event) -> None:
        if ev.kind == "gap":
            self.faults["gaps"] += 1
            self.faults["lost_lines"] += ev.count
        elif ev.kind == "reset":
            self.faults["device_resets"] += 1
            self.intake.new_epoch()
            self.journal.record(Decision.DEVICE_RESET, epoch=self.intake.epoch)
            self.link.restart_stream()

    # -- writing a calibration ------------------------------------------------------------------------
    def _may_write(self) -> bool:
        s, dev = self.settings, self.link.device
        return bool(s.daemon.recalibrate and s.write and dev is not None and dev.abilities.store)

    def _decide(self) -> None:
        """Ask the deciders whether to write a calibration now, and write what they solved."""
        if self.settings.daemon.keep is config.Keep.TRACKER:
            stored = self.tracking.keep(self.link.device, self.drift.calibration, self._may_write(), self.writer)
        else:
            session = self.recalibrator.poll(self._may_write(), self.drift.wants_calibration)
            stored = None if session is None else self._write(session)
        if stored is not None:
            self.drift.watch(stored, Decision.NEW_CALIBRATION)
            self.save()

    def _write(self, session: Session):
        """The recalibrator's solved session, written within the EEPROM budget, every command
        recorded in the write ledger first."""
        if not self.tracking.may_spend():
            self.faults["write_budget_waits"] += 1
            self.journal.record(Decision.BUDGET_WAIT, budget_per_day=self.settings.daemon.write_budget_per_day)
            return None
        ledgered = self.tracking.ledgered(self.link.device)
        stored = self.writer.write(ledgered, session)
        self.tracking.charge(ledgered, stored is not None)
        if stored is None:
            self.writer.recheck(self.link.device, self.drift.calibration)
        return stored

    # -- config reload ----------------------------------------------------------------------------------
    def reload(self) -> None:
        """SIGHUP: the config file again. Anything wrong with it — unreadable, not YAML, a bad
        value, a port no backend takes — is rejected as a whole and the running settings stay."""
        try:
            new = config.load(self.config_path, self.overrides)
            self.link.check_port(new)
        except ConfigError as exc:
            self.faults["config_rejected"] += 1
            self.journal.record(Decision.RELOAD_REJECTED, error=str(exc))
            return
        old, self.settings = self.settings, new
        self.journal.record(Decision.RELOADED, config=self.config_path)
        self.link.retarget(new)
        same_port = old.port == new.port
        self.recalibrator.use(new, keep_samples=same_port)  # another device: nothing collected is its
        self.tracking.use(new, keep_samples=same_port)
        if not same_port:
            self.drift.forget()
        self.drift.retune(new.daemon)

    # -- state ------------------------------------------------------------------------------------------
    def status(self) -> dict:
        return {
            "running": not self._stop.is_set(),
            "pid": os.getpid(),
            "port": self.settings.port,
            **self.link.status(),
            "uptime_s": round(self._wall() - self.started_wall, 3),
            **self.intake.status(),
            **self.recalibrator.status(),
            **self.drift.status(),
            **self.writer.status(),
            **self.tracking.status(),
            "faults": dict(sorted(self.faults.items())),
            "link": self.link.stats(),
            "capture": self.capture.stats(),
            "decisions": self.journal.recent(10),
        }

    def payload(self, generation: int, final: bool = False) -> dict:
        status = self.status()
        if final:
            status["running"] = False
        return {
            "kind": STATE_KIND,
            "generation": generation,
            "saved_utc": round(self._wall(), 3),
            "status": status,
            "resume": {
                "port": self.settings.port,
                **self.intake.to_state(),
                "faults": dict(self.faults),
                **self.drift.to_state(),
                **self.writer.status(),
                **self.recalibrator.to_state(),
                **self.tracking.to_state(),
                "decisions": list(self.journal.entries),
            },
        }

    def save(self, final: bool = False) -> bool:
        return self.keeper.save(lambda generation: self.payload(generation, final), self.settings.daemon.state_every_s)

    def resume(self) -> None:
        data = self.keeper.load()
        if data is None:
            return
        try:
            saved = Saved.parse(data, self.settings.gates)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            self.faults["state_refused"] += 1
            self.journal.record(Decision.STATE_UNUSABLE, error=why_unusable(exc))
            return
        if saved.port != self.settings.port:
            # another device's samples and calibration must not be mixed into this one's
            self.journal.record(Decision.STATE_OTHER_PORT, state_port=saved.port, port=self.settings.port)
            saved = saved.counters_only(Session(self.settings.gates, self.settings.model))
        self._restore(saved)
        self.tracking.resume(data["resume"].get("keeping") if saved.port == self.settings.port else None)
        self.journal.record(Decision.RESUMED, generation=saved.generation, samples=saved.samples,
                            source=self.keeper.loaded_from, note=self.keeper.load_note)
        if saved.replay_lines and scheme_of(self.settings.port) == "replay":
            # a replay is read from its start again: the lines the saved session already holds
            # are skipped, not counted twice
            self.intake.skip_replayed(saved.replay_lines)
            self.journal.record(Decision.REPLAY_SKIPS, skipped_lines=saved.replay_lines)

    def _restore(self, saved: Saved) -> None:
        self.recalibrator.restore(saved.session)
        self.drift.restore(saved.calibration, saved.monitor)
        self.intake.restore(saved.samples, saved.samples_in, saved.epoch)
        self.writer.restore(saved.last_calibration, saved.recalibrations)
        self.keeper.restore(saved.generation)
        self.faults.clear()
        self.faults.update(saved.faults)
        self.journal.restore(saved.decisions)


# -- signals -------------------------------------------------------------------------------------------
def _install_signals(stop: Callable[[], None], reload: Callable[[], None]) -> dict:
    """SIGTERM and SIGINT stop, SIGHUP reloads (in the main thread only); the handlers they
    replace, for ``_restore_signals`` once the daemon has stopped."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    wanted = {signal.SIGTERM: stop, signal.SIGINT: stop}
    if hasattr(signal, "SIGHUP"):
        wanted[signal.SIGHUP] = reload
    return {sig: signal.signal(sig, lambda *_, act=act: act()) for sig, act in wanted.items()}


def _restore_signals(previous: dict) -> None:
    """Put back what ``_install_signals`` replaced: a stopped daemon no longer takes a Ctrl-C or
    a SIGTERM meant for the process that ran it."""
    for sig, handler in previous.items():
        signal.signal(sig, handler)

