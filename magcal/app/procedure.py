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
from ..core.events import Identity
from ..devices.base import Device
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
    ended = ""
    while True:
        try:
            items = device.read(0.1)
        except EOFError:
            ended = "the recording ended"
            break
        session.add_many(items)
        now = clock()
        if on_progress and now - last_progress >= PROGRESS_EVERY_S:
            last_progress = now
            on_progress(session)
        if session.ready():
            break
        if now >= deadline:
            ended = f"timed out after {settings.timeout_s:g} s"
            break
    if not ended:
        try:
            device.stop()
        except DeviceError:
            pass  # the samples are in; a missed stop acknowledgement does not spoil them
    out.link = device.stats()
    if ended:
        session.update_estimate()
        failing = session.failing_gates()
        names = ", ".join(g.name for g in failing) or "none"
        detail = "; ".join(g.message for g in failing)
        session.fail(
            "timeout" if "timed out" in ended else "end_of_data",
            f"{ended} before every gate passed — failing: {names} ({detail})",
        )
        if on_progress:
            on_progress(session)
        return out
    result = session.solve()
    if on_progress:
        on_progress(session)
    if not result or session.status is Status.FAILED:
        return out
    if not (write and device.can_store):
        session.finish_without_write()
        return out
    return write_and_verify(device, session, out)


@dataclass
class Stored:
    """What writing one calibration to a device came to."""

    sent: Calibration  # as the device holds it (``device.prepare``)
    written: bool = False  # acknowledged and echoed back equal
    verified: bool = False  # and read back equal
    stored: Calibration | None = None  # what the device read back
    restored: bool | None = None  # after a mismatch: was the previous calibration put back?
    failure: str | None = None  # write_failed, verify_mismatch, verify_failed
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
        out.failure, out.message = "write_failed", str(exc)
        return out
    if not device.matches(sent, echoed):
        out.failure, out.message = "verify_mismatch", "the device echoed a different calibration than the one sent"
        out.restored = _restore(device, previous)
        return out
    out.written = True
    try:
        readback = device.read_calibration()
    except DeviceError as exc:
        out.failure, out.message = "verify_failed", f"could not read the calibration back: {exc}"
        return out
    out.stored = readback
    out.verified = device.matches(sent, readback)
    if not out.verified:
        out.failure = "verify_mismatch"
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
    if r.failure == "write_failed" or (r.failure == "verify_mismatch" and r.stored is None):
        session.fail(r.failure, r.message)  # refused, or the echo already differed
    else:
        session.stored()
        if r.failure == "verify_failed":
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
