"""The one small interface every device backend implements.

A ``Device`` is opened from a URL-like string by ``magcal.devices.open_device`` and then:

    ident = dev.open()                 # connect, identify → Identity
    dev.start(rate_hz)                 # start measuring/streaming
    for item in dev.read(timeout_s):   # Sample or Event, in arrival order
        ...
    dev.stop()
    dev.read_calibration()             # → Calibration | None (None: nothing stored)
    dev.write_calibration(cal)         # store; returns the calibration read back from the store
    dev.close()

Backends implement the underscored hooks; the base class owns counters and the "closed"
state, and turns a device that cannot store a calibration into a clear error. Backends differ
only in transport: the v1 serial protocol (serial ports, ``sim://``, ``replay://``, the emulated
board), the MotionCal dialect, and direct I2C.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import Counter
from typing import Iterable

from ..core.calibration import Calibration
from ..core.errors import DeviceError
from ..core.events import Event, Identity, Item


class Device(ABC):
    url: str = ""
    can_store: bool = True  # False for read-only sources (replay, CSV)

    def __init__(self, url: str):
        self.url = url
        self.identity: Identity | None = None
        self.counters: Counter = Counter()
        self._closed = False

    # -- public surface --------------------------------------------------------------------
    def open(self) -> Identity:
        self.identity = self._open()
        return self.identity

    def start(self, rate_hz: int | None = None) -> None:
        self._start(rate_hz)

    def stop(self) -> None:
        self._stop()

    def read(self, timeout_s: float = 0.1) -> list[Item]:
        """Whatever arrived within ``timeout_s`` (possibly nothing). Never raises for bad
        input on the link: that becomes counters and events. Raises PortUnavailable when
        the port has gone away, and EOFError at the end of a finite source."""
        return list(self._read(timeout_s))

    def read_calibration(self) -> Calibration | None:
        return self._read_calibration()

    def write_calibration(self, cal: Calibration) -> Calibration:
        """Store ``cal`` and return what the store holds afterwards (read back). The caller
        compares the two; a backend never claims success it has not read back."""
        if not self.can_store:
            raise DeviceError(f"{self.url}: this source cannot store a calibration")
        return self._write_calibration(cal)

    def prepare(self, cal: Calibration) -> Calibration:
        """``cal`` exactly as this device's store will hold it (fixed-point, float32 …)."""
        return cal

    def matches(self, sent: Calibration, stored: Calibration | None) -> bool:
        """Is ``stored`` (an echo or a read-back) the calibration that was sent?"""
        return stored is not None and sent.close_to(stored)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close()

    def stats(self) -> dict:
        return dict(self.counters)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- backend hooks ---------------------------------------------------------------------
    @abstractmethod
    def _open(self) -> Identity: ...

    @abstractmethod
    def _start(self, rate_hz: int | None) -> None: ...

    @abstractmethod
    def _stop(self) -> None: ...

    @abstractmethod
    def _read(self, timeout_s: float) -> Iterable[Item]: ...

    @abstractmethod
    def _read_calibration(self) -> Calibration | None: ...

    def _write_calibration(self, cal: Calibration) -> Calibration:
        raise DeviceError(f"{self.url}: this backend cannot store a calibration")

    @abstractmethod
    def _close(self) -> None: ...
