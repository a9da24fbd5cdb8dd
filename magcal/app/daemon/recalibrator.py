"""When to write a calibration, and writing it.

``Recalibrator`` decides *when*: it collects a session while the device holds no calibration or
the one it holds stopped fitting, and once the gates pass on the live estimate it solves; a
session that fails a gate is refused here. ``CalibrationWriter`` *writes*: the verified write of
``magcal.app.procedure`` (echo, read-back, the previous calibration put back on a mismatch), and
it remembers what it verified. Another decider hands its solved session to the same writer.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Callable

from ...core.calibration import Calibration
from ...core.errors import DeviceError
from ...core.events import Item
from ...devices.base import Device
from ...logic import failures
from ...logic.session import Session, Status
from ..procedure import Outcome, write_and_verify
from .journal import Decision, Journal

READY_EVERY = 100  # samples between gate checks while a recalibration waits for data


class Recalibrator:
    def __init__(self, settings, journal: Journal, faults: Counter):
        self.settings = settings
        self._journal = journal
        self._faults = faults
        self.session = Session(settings.gates, settings.model)
        self._since_ready = 0

    def take(self, item: Item, collected: bool = False) -> None:
        """A sample or event for the session; ``collected``: a good sample, counted towards the
        next gate check."""
        self.session.add(item)
        self._since_ready += collected

    def restart(self) -> None:
        """Collect afresh: what was collected belongs to another magnetic environment."""
        self.session = Session(self.settings.gates, self.settings.model)
        self._since_ready = 0

    def drifted(self, may_write: bool, say: bool = True) -> None:
        """The calibration held stopped fitting: collect for a new one (when writing is allowed);
        ``say``: this decider writes, so the journal says it collects."""
        self.restart()
        if say:
            self._journal.record(Decision.COLLECTING if may_write else Decision.REPORTING_ONLY)

    def poll(self, may_write: bool, wanted: bool) -> Session | None:
        """Every ``READY_EVERY`` collected samples, when a calibration is wanted and may be
        written: the session, solved, once its gates pass on the live estimate and the final fit;
        None otherwise (a refused one is counted and logged)."""
        if self._since_ready < READY_EVERY or not may_write or not wanted:
            return None
        self._since_ready = 0
        if not self.session.ready():
            return None
        session = self.session
        self.restart()
        self._journal.record(Decision.SOLVING, samples=len(session.kept), coverage=round(session.kept.coverage(), 3))
        session.solve()
        if session.status is Status.FAILED:
            self._faults["gate_failed"] += 1
            self._journal.record(Decision.REFUSED, **session.failure.to_dict(), message=session.failure_message)
            return None
        return session

    def use(self, settings, keep_samples: bool) -> None:
        """New settings: the samples stay and the new gates and model judge them, unless they
        belong to another device (``keep_samples`` False)."""
        self.settings = settings
        if keep_samples:
            self.session.retune(settings.gates, settings.model)
        else:
            self.restart()

    def status(self) -> dict:
        return {"coverage": round(self.session.kept.coverage(), 4), "session": self.session.progress()}

    def to_state(self) -> dict:
        return {"session": self.session.to_state()}

    def restore(self, session: Session) -> None:
        """A resumed session goes on collecting."""
        self.session = session
        self._since_ready = 0


class CalibrationWriter:
    def __init__(self, journal: Journal, faults: Counter, wall: Callable[[], float] = time.time):
        self._journal = journal
        self._faults = faults
        self._wall = wall
        self.last: dict | None = None  # the last calibration this daemon wrote and verified
        self.count = 0  # calibrations written and verified by this daemon

    def write(self, device: Device, session: Session) -> Calibration | None:
        """Write a solved session's calibration; what the device verifiably holds, or None."""
        outcome = Outcome(session=session, identity=device.identity)
        try:
            outcome = write_and_verify(device, session, outcome)
        except DeviceError as exc:  # anything write_and_verify did not turn into a failure
            session.fail(failures.WRITE_FAILED, str(exc))
        if session.status is Status.DONE and outcome.verified:
            self._verified(outcome.stored, session)
            return outcome.stored
        failure = session.failure or failures.WRITE_FAILED
        self._faults[failure.reason.value] += 1
        self._journal.record(Decision.NOT_WRITTEN, **failure.to_dict(), message=session.failure_message,
                             previous_restored=outcome.restored, discarded_unverified=outcome.discarded)
        return None

    def _verified(self, stored: Calibration, session: Session) -> None:
        rms_ut = float(session.result.rms_ut)
        self.count += 1
        self.last = {
            "calibration": stored.to_dict(),
            "written_utc": round(self._wall(), 3),
            "verified": True,
            "rms_ut": rms_ut,
            "samples": len(session.kept),
            "coverage": round(session.kept.coverage(), 4),
        }
        self._journal.record(Decision.WRITTEN, offset_ut=[round(x, 3) for x in stored.offset_ut],
                             field_ut=round(stored.field_ut, 3), rms_ut=round(rms_ut, 3))

    def recheck(self, device: Device, verified: Calibration | None) -> None:
        """After a failed write: is what the device holds still the calibration monitored?"""
        try:
            held = device.read_calibration()
        except DeviceError as exc:
            self._journal.record(Decision.RECORD_UNREADABLE, error=str(exc))
            return
        if held is None and verified is None:
            return
        if held is not None and verified is not None and device.matches(verified, held):
            return
        self._faults["device_record_unverified"] += 1
        self._journal.record(Decision.RECORD_UNVERIFIED)

    def status(self) -> dict:
        return {"last_calibration": self.last, "recalibrations": self.count}

    def restore(self, last: dict | None, count: int) -> None:
        self.last, self.count = last, count
