"""The tracking decider: keeps the device calibrated all along (``daemon.keep: tracker``).

Every good sample goes to a ``logic.keeper.Keeper`` (the tracker, the gates, the EEPROM
budget). Every ``READY_EVERY`` samples it is asked whether the tracker's calibration is worth a
write over the one the device verifiably holds: significantly better, every gate passed
(``logic.gates.clear_for_write``), budget left. If so it is written the one verified way
(``procedure.write_verified``: echo, read-back, the previous record put back on a mismatch) and
every EEPROM cycle it took is charged to the budget. When the drift monitor rings (the field
changed at once: a payload, a magnet) the tracker starts afresh, since what it remembers
belongs to the old field. Every EEPROM command goes through the write-ahead ledger
(``ledger.WriteLedger``, its one file) and the budget is charged from it: at start from what it
holds, a write a killed process left unresolved counted as spent.
"""

from __future__ import annotations

from collections import Counter
from typing import Callable

from ...core.calibration import Calibration
from ...core.errors import StateError
from ...devices.base import Device
from ...fit.accumulator import SphereAccumulator
from ...logic import failures
from ...logic.failures import Failure
from ...logic.gates import Clearance, Evidence, clear_for_write
from ...logic.keeper import Budget, DecisionReason, Keeper
from ..procedure import write_verified
from .journal import Decision, Journal
from .ledger import LedgeredDevice, WriteLedger

READY_EVERY = 100  # samples between decisions


class TrackingDecider:
    def __init__(self, settings, journal: Journal, faults: Counter, wall: Callable[[], float],
                 ledger: WriteLedger | None = None):
        self._journal, self._faults, self._wall = journal, faults, wall
        self.ledger = ledger
        self.ledger_open = False
        self.settings = settings
        self.keeper = self._new_keeper(settings)
        self._since = 0
        self.last_decision: dict | None = None

    @staticmethod
    def _new_keeper(settings) -> Keeper:
        d = settings.daemon
        return Keeper(settings.gates, Budget(d.write_budget_per_day, d.write_burst), d.monitor_alpha)

    def take(self, field_ut, t_s: float) -> None:
        """A good sample."""
        self.keeper.add(field_ut, t_s)
        self._since += 1

    def restart(self, may_write: bool | None = None) -> None:
        """The drift monitor rang: the tracker starts afresh (``Keeper.restart``). ``may_write``
        given: this decider keeps the device, and the journal says what happens next."""
        self.keeper.restart()
        if may_write is not None:
            self._journal.record(Decision.TRACKER_RESTARTED if may_write else Decision.REPORTING_ONLY)

    def _clearance(self, cal: Calibration, est) -> Clearance:
        """The gates' decision, on the tracker's own evidence (its memory: samples, directions,
        the sphere condition the session's gate uses; the residual and offset σ of ``est``, the
        estimate the keeper checked, whose σ are at least fit's on that memory)."""
        trk = self.keeper.tracker
        est = est or trk.estimate
        _, m, _, _ = trk.memory.samples()
        acc = SphereAccumulator()
        acc.add_batch(m)
        sphere = acc.solve(max_condition=float("inf"))
        ev = Evidence(offset_ut=tuple(cal.offset_ut), field_ut=cal.field_ut, rms_ut=est.noise_ut,
                      offset_sigma_ut=tuple(est.offset_sigma_ut), n_used=len(m), coverage=trk.coverage(),
                      condition=sphere.condition if sphere else None)
        return clear_for_write(self.settings.gates, ev)

    def poll(self, device: Device | None, held: Calibration | None, may_write: bool) -> Calibration | None:
        """Every ``READY_EVERY`` samples, when writing is allowed: write the tracker's calibration
        if the keeper says so and the gates clear it. What the device then verifiably holds, or
        None when nothing was written."""
        if self._since < READY_EVERY or not may_write or device is None or not self.ledger_open:
            return None
        self._since = 0
        now = self._wall()
        decision = self.keeper.decide(held, now)
        self.last_decision = decision.to_dict()
        if decision.reason is DecisionReason.BUDGET:
            self._faults["write_budget_waits"] += 1
        if not decision.write:
            return None
        clearance = self._clearance(decision.calibration, decision.estimate)
        if not clearance.allowed:
            self._journal.record(Decision.REFUSED, **Failure.of_gate(clearance.blocking[0].name).to_dict(),
                                 message=clearance.summary())
            return None
        self._journal.record(Decision.KEEPING, reason=decision.reason.value, message=decision.message)
        ledgered = self.ledgered(device)
        result = write_verified(ledgered, decision.calibration, clearance)
        # every command that may have reached the EEPROM is charged: the write, and putting the
        # old record back or erasing the failed one
        self.charge(ledgered, result.verified, now)
        if result.verified:
            return result.stored
        failure = result.failure or failures.WRITE_FAILED
        self._faults[failure.reason.value] += 1
        self._journal.record(Decision.NOT_WRITTEN, **failure.to_dict(), message=result.message,
                             previous_restored=result.restored)
        return None

    def open_ledger(self) -> bool:
        """At start, once the state is resumed: the budget as the ledger says it was spent (an
        unresolved write counted). A ledger that cannot be opened is said once; nothing is then
        written, since nothing written could be counted."""
        if self.ledger is None:
            return False
        try:
            history = self.ledger.open()
        except StateError as exc:
            self._faults["ledger_unavailable"] += 1
            self._journal.record(Decision.LEDGER_UNAVAILABLE, error=str(exc))
            return False
        self.ledger_open = True
        self.keeper.charge_history(history.spent_at_s, history.verified, history.failed)
        if history.unresolved:
            self._journal.record(Decision.WRITE_INTERRUPTED, operations=len(history.unresolved),
                                 eeprom_cycles=history.cycles)
        return history.cycles > 0

    def close_ledger(self) -> None:
        if self.ledger is not None:
            self.ledger.close()
        self.ledger_open = False

    def may_spend(self) -> bool:
        """May another decider write now (the ledger open, a token in the budget)?"""
        return self.ledger_open and self.keeper.affords(self._wall())

    def ledgered(self, device: Device) -> LedgeredDevice:
        """``device`` with every EEPROM command recorded in the ledger before it is sent."""
        return LedgeredDevice(device, self.ledger)

    def charge(self, ledgered: LedgeredDevice, verified: bool, now: float | None = None) -> None:
        """The write is over: resolved in the ledger, its commands charged to the budget."""
        cycles = ledgered.resolve(verified)
        self.keeper.spent(self._wall() if now is None else now, cycles, verified)

    def keep(self, device: Device | None, held: Calibration | None, may_write: bool, writer) -> Calibration | None:
        """``poll``, and what was written recorded on the daemon's ``writer`` (``record_on``)."""
        stored = self.poll(device, held, may_write)
        if stored is not None:
            self.record_on(writer, stored)
        return stored

    def use(self, settings, keep_samples: bool) -> None:
        """New settings: new gates, budget and significance; what the tracker remembers stays,
        unless it belongs to another device."""
        old, self.settings = self.keeper, settings
        self.keeper = self._new_keeper(settings)
        if keep_samples:
            self.keeper.load_state(old.to_state())

    def record_on(self, writer, stored: Calibration) -> None:
        """Tell the daemon's writer what was verified, so status and state show it as its own."""
        est = self.keeper.tracker.estimate
        writer.count += 1
        writer.last = {"calibration": stored.to_dict(), "written_utc": round(self._wall(), 3), "verified": True,
                       "rms_ut": est.noise_ut, "samples": est.buffered, "coverage": round(est.coverage, 4),
                       "by": "tracker"}
        self._journal.record(Decision.WRITTEN, offset_ut=[round(x, 3) for x in stored.offset_ut],
                             field_ut=round(stored.field_ut, 3), rms_ut=round(est.noise_ut, 3))

    def status(self) -> dict:
        return {"keeping": {**self.keeper.status(), "last_decision": self.last_decision}}

    def to_state(self) -> dict:
        return {"keeping": self.keeper.to_state()}

    def resume(self, state: dict | None) -> None:
        """Resume the keeper saved in the state file; a malformed one is counted and dropped
        (the tracker starts afresh, nothing else is lost)."""
        if state is None:
            return
        try:
            self.keeper.load_state(state)
        except ValueError as exc:
            self.keeper = self._new_keeper(self.settings)
            self._faults["state_refused"] += 1
            self._journal.record(Decision.STATE_UNUSABLE, error=f"keeping: {exc}")
