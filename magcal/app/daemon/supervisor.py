"""The link supervisor: builds the device once, connects it (and again, with back-off, after it is
lost), reads it, notices a stall, restarts the stream after a device reset, drains it at stop.

The device object lives as long as its port settings: a reconnection opens the same device
again (a simulated board, a recording resume where they were), a change of port, dialect or baud
rate builds a new one. A port string no backend takes is a ``PortError`` at the first connection,
not a reason to retry.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass
from typing import Callable

from ...core.calibration import Calibration, StoredRecord
from ...core.errors import DeviceError, PortUnavailable
from ...core.events import Identity, Item
from ...devices.base import Device
from ...devices.port import parse_port, scheme_of
from ...recordings.capture import CaptureWriteError
from .journal import Decision, Journal

TAP_SCHEMES = ("sim", "emu", "replay", "serial")  # backends that take a capture tap (either dialect)
DRAIN_READS = 20  # at stop: reads of 20 ms that take in what the device had already sent


@dataclass(frozen=True)
class Connected:
    """A connection made: who answered and the calibration the device holds. ``knows_record`` is
    False for a source that holds none of its own (a recording)."""

    identity: Identity
    stored: Calibration | None
    knows_record: bool = True


# what a link's counters say went wrong on the line, shown among the daemon's faults (gaps and
# lost lines come as events, and the daemon counts those itself)
LINE_DEFECTS = ("noise_bytes", "torn_lines", "overlong_lines", "malformed_lines", "bad_checksums", "bad_syntax",
                "unknown_types", "duplicate_lines", "out_of_sequence_lines", "sequence_resyncs", "hellos_refused",
                "record_crc_errors", "record_invalid")


class LinkSupervisor:
    def __init__(self, settings, journal: Journal, faults: Counter, *, open_device: Callable[..., Device],
                 options: dict | None = None, tap: Callable[[], object] = lambda: None,
                 on_capture_error: Callable[[CaptureWriteError], None] = lambda exc: None,
                 clock: Callable[[], float] = time.monotonic):
        self.settings = settings
        self._journal = journal
        self._faults = faults
        self._open_device = open_device
        self._options = dict(options or {})  # e.g. reply_timeout_s, for tests
        self._tap = tap
        self._capture_error = on_capture_error
        self._clock = clock
        self._built: Device | None = None  # kept across reconnections
        self.device: Device | None = None  # the connected device, or None
        self.ended = False  # a finite source reached its end
        self._retry = 0
        self._last_data = 0.0
        self._counted: Counter = Counter()  # the built device's line defects already in the faults
        self.record: StoredRecord | None = None  # what the device's store held at the last connect

    @property
    def connected(self) -> bool:
        return self.device is not None

    # -- connecting ------------------------------------------------------------------------------
    def backoff_s(self) -> float:
        d = self.settings.daemon
        return min(d.reconnect_max_s, d.reconnect_min_s * (2 ** min(self._retry - 1, 30)))

    def connect(self) -> Connected | None:
        """Open, identify, read the stored calibration, start streaming; None when it failed
        (counted, logged, and the next attempt backs off)."""
        s = self.settings
        dev = None
        try:
            dev = self._built = self._built or self._build()
            ident = dev.open()
            connected = self._read_stored(dev, ident)
            dev.start(s.rate_hz)
        except (DeviceError, OSError, CaptureWriteError) as exc:
            if isinstance(exc, CaptureWriteError):
                self._capture_error(exc)
            self._retry += 1
            self._faults["connect_failed"] += 1
            if dev is not None:
                _close_quietly(dev)
            self._journal.record(Decision.CONNECT_FAILED, port=s.port, error=str(exc),
                                 retry_in_s=round(self.backoff_s(), 3))
            return None
        self.device = dev
        self.ended = False
        self._last_data = self._clock()
        return connected

    def _build(self) -> Device:
        s = self.settings
        self._counted = Counter()  # a new device counts from nothing
        options = dict(self._options)
        tap = self._tap()
        if tap is not None and scheme_of(s.port) in TAP_SCHEMES:
            options["tap"] = tap
        if s.baud != 115200 and scheme_of(s.port) == "serial":  # a serial-port setting
            options["baud"] = s.baud
        return self._open_device(s.port, dialect=s.dialect, **options)  # PortError: no retry helps

    def _read_stored(self, dev: Device, ident: Identity) -> Connected:
        """The calibration the device holds; a record it holds that cannot be used (corrupt, or
        invalid behind a valid CRC) is logged and counted, and taken as none (a recalibration,
        when allowed, replaces it)."""
        if not dev.abilities.store:
            return Connected(ident, None, knows_record=False)
        try:
            self.record = dev.read_stored()
        except PortUnavailable:
            raise
        except DeviceError as exc:
            self._journal.record(Decision.STORED_UNREADABLE, error=str(exc))
            return Connected(ident, None)
        if self.record.problem:
            self._faults[f"stored_record_{self.record.state.value}"] += 1
            self._journal.record(Decision.STORED_UNUSABLE, state=self.record.state.value, problem=self.record.problem)
        return Connected(ident, self.record.calibration)

    # -- reading ---------------------------------------------------------------------------------
    def read(self, timeout_s: float) -> list[Item]:
        """What the device sent; [] when nothing came or the link was lost (then disconnected).
        At the end of a finite source: [] and ``ended``. The line defects the device counted
        meanwhile go into the faults."""
        try:
            return self.device.read(timeout_s)
        except EOFError:
            self.ended = True
        except CaptureWriteError as exc:
            self._capture_error(exc)
        except (DeviceError, OSError) as exc:
            self.lose(exc)
        finally:
            self.count_defects()
        return []

    def count_defects(self) -> None:
        """Add the line defects the built device counted since the last look to the faults."""
        dev = self._built
        if dev is None:
            return
        now = Counter({k: v for k, v in dev.stats().items() if k in LINE_DEFECTS})
        self._faults.update(now - self._counted)
        self._counted = now

    def heard(self) -> None:
        """A sample arrived: the link is alive, and the next loss starts its back-off afresh."""
        self._last_data = self._clock()
        self._retry = 0

    def stalled(self, now: float) -> bool:
        """No sample for ``daemon.stall_s`` (events do not count): the link is dropped."""
        quiet = now - self._last_data
        if not self.connected or quiet <= self.settings.daemon.stall_s:
            return False
        self._faults["stalls"] += 1
        self.lose(DeviceError(f"no data for {quiet:.1f} s (stall)"))
        return True

    def restart_stream(self) -> None:
        """After a device reset: ask it to stream again."""
        if self.device is None:
            return
        try:
            self.device.start(self.settings.rate_hz)
        except (DeviceError, OSError) as exc:
            self.lose(exc)

    def drain(self, handle: Callable[[list[Item]], None]) -> None:
        """Stopping: ask the device to stop streaming and hand over what already arrived, so a
        clean stop leaves no received sample unprocessed. A recording has nothing in flight:
        reading on would only consume more of it, which a restart resumes from."""
        dev = self.device
        if dev is None or not dev.abilities.live:
            return
        try:
            for _ in range(2):  # a full disk found while stopping is reported, and stop asked again
                try:
                    dev.stop()
                    break
                except PortUnavailable:
                    return
                except DeviceError:
                    break
                except CaptureWriteError as exc:
                    self._capture_error(exc)
            for _ in range(DRAIN_READS):
                try:
                    items = dev.read(0.02)
                except CaptureWriteError as exc:
                    self._capture_error(exc)
                    continue
                if not items:
                    break
                handle(items)
        except (DeviceError, OSError, EOFError):
            pass

    # -- losing and dropping ------------------------------------------------------------------------
    def lose(self, exc: Exception) -> None:
        kind = "port_lost" if isinstance(exc, (PortUnavailable, OSError)) else "link_error"
        self._faults[kind] += 1
        self._retry = max(self._retry, 1)
        self.disconnect(Decision.LINK_LOST, f"link lost: {exc}")

    def disconnect(self, decision: Decision = Decision.DISCONNECTED, why: str = "") -> None:
        if self.device is None:
            return
        dev, self.device = self.device, None
        self.count_defects()
        _close_quietly(dev)
        self._journal.record(decision, why=why)

    def check_port(self, settings) -> None:
        """ConfigError (PortError) when new settings name another port that no backend takes."""
        if settings.port and settings.port != self.settings.port:
            parse_port(settings.port)

    def retarget(self, new) -> None:
        """New settings: reconnect when the link's own ones changed; another port, dialect or
        baud rate is another device."""
        old, self.settings = self.settings, new
        if (old.port, old.dialect, old.baud, old.rate_hz) != (new.port, new.dialect, new.baud, new.rate_hz):
            self.disconnect(Decision.DISCONNECTED, "settings changed: reconnecting")
        if (old.port, old.dialect, old.baud) != (new.port, new.dialect, new.baud):
            self._built = None

    def close(self) -> None:
        self.disconnect(Decision.DISCONNECTED, "daemon stopping")

    # -- reporting -----------------------------------------------------------------------------------
    def status(self) -> dict:
        ident = self.device.identity if self.device is not None else None
        return {"connected": self.connected, "device": ident.to_dict() if ident else None,
                "stored_record": None if self.record is None else self.record.to_dict()}

    def stats(self) -> dict:
        """The counters of the device (over every connection to it, connected now or not)."""
        return self._built.stats() if self._built is not None else {}

    def matches(self, sent: Calibration, stored: Calibration | None) -> bool:
        """The connected device's own comparison of two calibrations (its precision)."""
        return self.device is not None and self.device.matches(sent, stored)


def _close_quietly(dev: Device) -> None:
    try:
        dev.close()
    except (DeviceError, OSError):
        pass
