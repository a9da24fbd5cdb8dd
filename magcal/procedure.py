"""One calibration, end to end, on any device: identify → stream → collect → fit → write → verify.

The loop that joins a ``Device`` (I/O) to a ``Session`` (pure logic). The clock is passed in by
the caller (the CLI or the daemon own the effects), so tests can drive it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

from .calibration import Calibration
from .config import Settings
from .devices.base import Device, Identity
from .errors import DeviceError
from .session import Session, Status

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


def write_and_verify(device: Device, session: Session, out: Outcome) -> Outcome:
    """Write, compare the echo, read back, compare again. On a mismatch the calibration that
    was stored before is put back (best effort) so a bad one is not left on the device."""
    cal = device.prepare(session.calibration)
    try:
        previous = device.read_calibration()
    except DeviceError:
        previous = None
    session.begin_write()
    try:
        echoed = device.write_calibration(cal)
    except DeviceError as exc:  # refused, no reply, port lost
        session.fail("write_failed", str(exc))
        return out
    if not device.matches(cal, echoed):
        session.fail("verify_mismatch", "the device echoed a different calibration than the one sent")
        _restore(device, previous, out)
        return out
    out.written = True
    session.stored()
    try:
        readback = device.read_calibration()
    except DeviceError as exc:
        session.fail("verify_failed", f"could not read the calibration back: {exc}")
        return out
    out.stored = readback
    ok = device.matches(cal, readback)
    out.verified = ok
    session.verified(ok, "the calibration read back from the device differs from the one sent")
    if not ok:
        out.written = False
        _restore(device, previous, out)
    out.link = device.stats()
    return out


def _restore(device: Device, previous: Calibration | None, out: Outcome) -> None:
    out.link = device.stats()
    if previous is None:
        out.restored = False
        return
    try:
        out.restored = device.matches(previous, device.write_calibration(previous))
    except DeviceError:
        out.restored = False
