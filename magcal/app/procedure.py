"""One calibration, end to end, on any device: identify → stream → collect → fit → write → verify.

The loop that joins a ``Device`` (I/O) to a ``Session`` (pure logic). The clock is passed in by
the caller (the CLI or the daemon own the effects), so tests can drive it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

from ..core.calibration import Calibration
from ..core.errors import DeviceError
from ..core.events import Code, Identity
from ..devices.base import Device, batches
from ..logic.session import Session, Status
from .config import Settings

PROGRESS_EVERY_S = 0.25


class Ended(Code):
    """Why collecting stopped before every gate passed (the session's failure code)."""

    TIMEOUT = "timeout"
    END_OF_DATA = "end_of_data"


class WriteFailure(Code):
    """Why a calibration is not on the device as sent (the session's failure code)."""

    WRITE_FAILED = "write_failed"  # refused, no reply, port lost
    VERIFY_MISMATCH = "verify_mismatch"  # the echo or the read-back differs
    VERIFY_FAILED = "verify_failed"  # written, but it could not be read back


@dataclass
class Outcome:
    session: Session
    identity: Identity | None
    written: bool = False
    verified: bool = False
    stored: Calibration | None = None  # what the device read back
    restored: bool | None = None  # after a failed verification: was the old calibration put back?
    link: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.session.status is Status.DONE

    def to_dict(self) -> dict:
        s = self.session
        r = s.result
        quality = {
            "samples": int(s.counters["samples_in"]),
            "kept": len(s.kept),
            "coverage": round(s.kept.coverage(), 4),
            "gates": [g.to_dict() for g in (s.final_gates if r else s.live_gates())],
            "session": dict(s.counters),
            "link": self.link,
        }
        out = {
            "status": s.status.value,
            "failure": s.failure,
            "message": s.failure_message,
            "calibration": None,
            "quality": quality,
            "written": self.written,
            "verified": self.verified,
            "restored_previous": self.restored,
            "device": self.identity.to_dict() if self.identity else None,
        }
        if r:
            d = r.to_dict()
            out["calibration"] = d["calibration"]
            out["model"] = d.get("model")
            out["uncertainty"] = d.get("uncertainty")
            quality.update({k: d[k] for k in ("rms_ut", "n_used", "outliers", "reason") if k in d})
        return out


def calibrate(
    device: Device,
    settings: Settings,
    *,
    write: bool = True,
    clock: Callable[[], float] = time.monotonic,
    on_progress: Callable[[Session], None] | None = None,
    session: Session | None = None,
) -> Outcome:
    """Run one calibration on an *opened* device. Never raises for gate or fit failures: the
    outcome says what happened. Device errors during the write are recorded as failures too —
    nothing is reported as written unless the device acknowledged it, and nothing as verified
    unless the read-back matches."""
    session = session or Session(settings.gates, settings.model)
    out = Outcome(session=session, identity=device.identity)
    deadline = clock() + settings.timeout_s
    last_progress = 0.0
    device.start(settings.rate_hz)
    ended: Ended | None = None
    for items in batches(device, 0.1):
        session.add_many(items)
        now = clock()
        if on_progress and now - last_progress >= PROGRESS_EVERY_S:
            last_progress = now
            on_progress(session)
        if session.ready():
            break
        if now >= deadline:
            ended = Ended.TIMEOUT
            break
    else:
        ended = Ended.END_OF_DATA
    if ended is None:
        try:
            device.stop()
        except DeviceError:
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


def _give_up(session: Session, ended: Ended, timeout_s: float) -> None:
    session.update_estimate()
    failing = session.failing_gates()
    names = ", ".join(g.name for g in failing) or "none"
    detail = "; ".join(g.message for g in failing)
    why = f"timed out after {timeout_s:g} s" if ended is Ended.TIMEOUT else "the recording ended"
    session.fail(ended, f"{why} before every gate passed — failing: {names} ({detail})")


@dataclass
class Stored:
    """What writing one calibration to a device came to."""

    sent: Calibration  # as the device holds it (``device.prepare``)
    written: bool = False  # acknowledged and echoed back equal
    verified: bool = False  # and read back equal
    stored: Calibration | None = None  # what the device read back
    restored: bool | None = None  # after a mismatch: was the previous calibration put back?
    failure: WriteFailure | None = None
    message: str = ""


def store_verified(device: Device, cal: Calibration) -> Stored:
    """Write, compare the echo, read back, compare again — on any opened device that can store.
    On a mismatch the calibration that was stored before is put back (best effort) so a bad one
    is not left on the device. Device errors become failures here, never exceptions."""
    sent = device.prepare(cal)
    out = Stored(sent=sent)
    try:
        previous = device.read_calibration()
    except DeviceError:
        previous = None
    try:
        echoed = device.write_calibration(sent)
    except DeviceError as exc:  # refused, no reply, port lost
        out.failure, out.message = WriteFailure.WRITE_FAILED, str(exc)
        return out
    if not device.matches(sent, echoed):
        out.failure = WriteFailure.VERIFY_MISMATCH
        out.message = "the device echoed a different calibration than the one sent"
        out.restored = _restore(device, previous)
        return out
    out.written = True
    try:
        readback = device.read_calibration()
    except DeviceError as exc:
        out.failure, out.message = WriteFailure.VERIFY_FAILED, f"could not read the calibration back: {exc}"
        return out
    out.stored = readback
    out.verified = device.matches(sent, readback)
    if not out.verified:
        out.failure = WriteFailure.VERIFY_MISMATCH
        out.message = "the calibration read back from the device differs from the one sent"
        out.written = False
        out.restored = _restore(device, previous)
    return out


def write_and_verify(device: Device, session: Session, out: Outcome) -> Outcome:
    """``store_verified`` for a session's result, with the session taken through writing →
    verifying → done (or failed with the reason)."""
    session.begin_write()
    r = store_verified(device, session.calibration)
    out.written, out.verified, out.stored, out.restored = r.written, r.verified, r.stored, r.restored
    out.link = device.stats()
    if r.failure is WriteFailure.WRITE_FAILED or (r.failure is WriteFailure.VERIFY_MISMATCH and r.stored is None):
        session.fail(r.failure, r.message)  # refused, or the echo already differed
    else:
        session.stored()
        if r.failure is WriteFailure.VERIFY_FAILED:
            session.fail(r.failure, r.message)
        else:
            session.verified(r.verified, r.message)
    return out


def _restore(device: Device, previous: Calibration | None) -> bool:
    if previous is None:
        return False
    try:
        return device.matches(previous, device.write_calibration(previous))
    except DeviceError:
        return False
