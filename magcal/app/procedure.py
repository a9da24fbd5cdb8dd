"""One calibration, end to end, on any device: identify → stream → collect → fit → write → verify.

The loop that joins a ``Device`` (I/O) to a ``Session`` (pure logic). The clock is passed in by
the caller (the CLI or the daemon own the effects), so tests can drive it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

from ..core.calibration import Calibration, RecordState, StoredRecord
from ..core.errors import DeviceError
from ..core.events import Identity
from ..devices.base import Device, batches
from ..logic import failures
from ..logic.failures import Failure, Reason
from ..logic.gates import Clearance
from ..logic.session import Session, Status
from .config import Settings

PROGRESS_EVERY_S = 0.25


@dataclass
class Outcome:
    session: Session
    identity: Identity | None
    written: bool = False
    verified: bool = False
    stored: Calibration | None = None  # what the device read back
    restored: bool | None = None  # after a failed verification: was the old calibration put back?
    link: dict = field(default_factory=dict)
    discarded: bool = False  # the record that failed verification was discarded (nothing stored)
    collect_s: float = 0.0  # time spent collecting samples (on the caller's clock)

    @property
    def ok(self) -> bool:
        return self.session.status is Status.DONE

    def to_dict(self) -> dict:
        """One flat shape, with the keys ``fit --json`` uses for the same quantities."""
        s = self.session
        n_in = int(s.counters["samples_in"])
        out = {
            "status": s.status.value,
            **failures.fields(s.failure),
            "message": s.failure_message,
            "model": None,
            "calibration": None,
            "uncertainty": None,
            "rms_ut": None,
            "n_samples": n_in,
            "n_kept": len(s.kept),
            "n_used": None,
            "outliers": [],
            "coverage": round(s.kept.coverage(), 4),
            "rate_hz": self.identity.rate_hz if self.identity and self.identity.rate_hz else None,
            "measured_rate_hz": round(n_in / self.collect_s, 2) if self.collect_s > 0 else None,
            "gates": [g.to_dict() for g in (s.final_gates if s.result else s.live_gates())],
            "evidence": _evidence_dict(s.clearance.evidence) if s.clearance is not None else None,
            "written": self.written,
            "verified": self.verified,
            "restored_previous": self.restored,
            "discarded_unverified": self.discarded,
            "device": self.identity.to_dict() if self.identity else None,
            "counters": dict(s.counters),
            "link": self.link,
        }
        if s.result:
            d = s.result.to_dict()
            out.update({k: d[k] for k in ("model", "calibration", "uncertainty", "rms_ut", "n_used", "outliers",
                                          "reason") if k in d})
        return out


def _evidence_dict(ev) -> dict:
    """What the gates judged, in the shape ``fit --json`` gives it (``fit.evidence``)."""
    sigma = ev.offset_sigma_ut
    return {"n_used": ev.n_used, "coverage": ev.coverage, "condition": ev.condition, "rms_ut": ev.rms_ut,
            "offset_sigma_ut": None if sigma is None else [float(v) for v in sigma]}


def _collect(device: Device, session: Session, settings: Settings, clock, on_progress,
             every_s: float = PROGRESS_EVERY_S) -> Failure | None:
    """Read until every gate passes (None), or the source ends or the time is up (why, unless
    every gate passes on what was collected by then)."""
    deadline = clock() + settings.timeout_s
    last_progress = 0.0
    for items in batches(device, min(0.1, every_s)):
        session.add_many(items)
        now = clock()
        if on_progress and now - last_progress >= every_s:
            last_progress = now
            on_progress(session)
        if session.ready():
            return None
        if now >= deadline:
            return _unless_ready(session, failures.TIMEOUT)
    return _unless_ready(session, failures.END_OF_DATA)


def _unless_ready(session: Session, ended: Failure) -> Failure | None:
    """The gates are judged at fixed sample counts; the last samples may have passed them all."""
    session.update_estimate()
    return None if session.counters["samples_in"] and not session.failing_gates() else ended


def calibrate(
    device: Device,
    settings: Settings,
    *,
    write: bool = True,
    clock: Callable[[], float] = time.monotonic,
    on_progress: Callable[[Session], None] | None = None,
    session: Session | None = None,
    progress_every_s: float = PROGRESS_EVERY_S,
) -> Outcome:
    """Run one calibration on an *opened* device. Never raises for gate or fit failures: the
    outcome says what happened. Device errors during the write are recorded as failures too —
    nothing is reported as written unless the device acknowledged it, and nothing as verified
    unless the read-back matches. ``on_progress(session)`` is called at most every
    ``progress_every_s`` while collecting (the live view asks for more than the terminal), and
    once after solving."""
    session = session or Session(settings.gates, settings.model)
    device.start(settings.rate_hz)
    out = Outcome(session=session, identity=device.identity)  # after start: with the rate it took
    t0 = clock()
    ended = _collect(device, session, settings, clock, on_progress, progress_every_s)
    out.collect_s = clock() - t0
    if ended is None:
        try:
            device.stop()
        except (DeviceError, OSError):
            pass  # the samples are in; a missed stop acknowledgement does not spoil them
    out.link = device.stats()
    if ended is not None:
        _give_up(session, ended, settings.timeout_s)
        if on_progress:
            on_progress(session)
        return out
    result = session.solve()
    if on_progress:
        on_progress(session)
    if not result or session.status is Status.FAILED:
        return out
    if not (write and device.abilities.store):
        session.finish_without_write()
        return out
    return write_and_verify(device, session, out)


def _give_up(session: Session, ended: Failure, timeout_s: float) -> None:
    failing = session.failing_gates()
    names = ", ".join(g.name for g in failing)
    detail = "; ".join(g.message for g in failing)
    why = f"timed out after {timeout_s:g} s" if ended.reason is Reason.TIMEOUT else "the recording ended"
    session.fail(ended, f"{why} before every gate passed — failing: {names} ({detail})")


@dataclass
class WriteResult:
    """What writing one calibration to a device came to."""

    sent: Calibration  # as the device holds it (``device.prepare``)
    written: bool = False  # acknowledged and echoed back equal
    verified: bool = False  # and read back equal
    stored: Calibration | None = None  # what the device read back
    restored: bool | None = None  # after a failure: is the store back to what it held before?
    failure: Failure | None = None  # a write's reason: WRITE_FAILED, VERIFY_MISMATCH, VERIFY_FAILED
    message: str = ""
    discarded: bool = False  # the record that failed was discarded: the device holds no calibration
    previous: StoredRecord | None = None  # what the store held before (None: it could not be read)


def write_verified(device: Device, cal: Calibration, clearance: Clearance) -> WriteResult:
    """Write, compare the echo, read back, compare again — on any opened device that can store.
    When that fails after the store was touched, what was stored before is put back: the earlier
    calibration, or nothing when there was none (or none usable) — an unverified record is never
    left in place to be shown as the calibration. Device errors become failures, never exceptions.

    ``clearance`` is the gates' decision on ``cal`` (``logic.gates.clear_for_write``): every
    path that writes comes through here, and nothing is written without one that allows it."""
    if not (clearance.allowed and clearance.covers(cal.offset_ut, cal.field_ut)):
        raise ValueError("refusing to write a calibration the gates did not clear: " + clearance.summary())
    out = WriteResult(sent=device.prepare(cal))
    try:
        out.previous = device.read_stored()
    except DeviceError:
        out.previous = None
    try:
        echoed = device.write_calibration(out.sent)
    except DeviceError as exc:  # refused, no reply, port lost, or the store holds no calibration after W
        out.failure, out.message = failures.WRITE_FAILED, str(exc)
        if _touched(device, out.previous):
            _undo(device, out)
        return out
    if not device.matches(out.sent, echoed):
        out.failure = failures.VERIFY_MISMATCH
        out.message = "the device echoed a different calibration than the one sent"
        _undo(device, out)
        return out
    out.written = True
    try:
        readback = device.read_calibration()
    except DeviceError as exc:
        out.failure, out.message = failures.VERIFY_FAILED, f"could not read the calibration back: {exc}"
        return out
    out.stored = readback
    out.verified = device.matches(out.sent, readback)
    if not out.verified:
        out.failure = failures.VERIFY_MISMATCH
        out.message = "the calibration read back from the device differs from the one sent"
        out.written = False
        _undo(device, out)
    return out


def _touched(device: Device, previous: StoredRecord | None) -> bool:
    """After a failed write: does the store hold something other than before (or is it unknown)?"""
    try:
        now = device.read_stored()
    except DeviceError:
        return False  # the device cannot be asked: nothing more can be done through it
    if previous is None or now.state is not previous.state:
        return True
    return now.calibration is not None and not device.matches(previous.calibration, now.calibration)


def _undo(device: Device, out: WriteResult) -> None:
    """Put back the calibration stored before; when there was none, or it cannot be put back,
    discard the record that failed so that nothing unverified is left in place."""
    prev = out.previous
    if prev is not None and prev.calibration is not None:
        try:
            if device.matches(prev.calibration, device.write_calibration(prev.calibration)):
                out.restored = True
                return
        except DeviceError:
            pass
    try:
        out.discarded = device.discard_calibration().state is RecordState.NONE
    except DeviceError as exc:
        out.message += f"; the record that failed could not be discarded either: {exc}"
    out.restored = out.discarded and prev is not None and prev.state is RecordState.NONE


def write_and_verify(device: Device, session: Session, out: Outcome) -> Outcome:
    """``write_verified`` for a session's result, with the session taken through writing →
    verifying → done (or failed with the reason)."""
    session.begin_write()
    r = write_verified(device, session.calibration, session.clearance)
    out.written, out.verified, out.stored, out.restored = r.written, r.verified, r.stored, r.restored
    out.discarded = r.discarded
    out.link = device.stats()
    if r.failure == failures.WRITE_FAILED or (r.failure == failures.VERIFY_MISMATCH and r.stored is None):
        session.fail(r.failure, r.message)  # refused, or the echo already differed
    else:
        session.written()
        if r.failure == failures.VERIFY_FAILED:
            session.fail(r.failure, r.message)
        else:
            session.verified(r.verified, r.message)
    return out
