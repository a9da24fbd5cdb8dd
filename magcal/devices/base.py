"""The one small interface every device backend implements.

A ``Device`` is built from a port string by ``magcal.devices.open_device`` and then:

    ident = dev.open()                 # connect, identify → Identity
    dev.start(rate_hz)                 # start measuring/streaming
    for item in dev.read(timeout_s):   # Sample or Event, in arrival order
        ...
    dev.stop()
    dev.read_calibration()             # → Calibration | None (None: nothing usable stored)
    dev.read_stored()                  # → StoredRecord: the calibration, or none/corrupt/invalid and why
    dev.write_calibration(cal)         # store; returns the calibration read back from the store
    dev.close()                        # and open() again later: that is how a link reconnects

What a device can do beyond reading it declares in ``abilities`` (an ``Abilities`` value):
callers ask it, never probe for attributes. A device asked for an ability it has not raises
``Unsupported``.

Backends implement the underscored hooks. ``read`` is the one read loop: it waits, up to its
timeout, on the one hook ``_receive`` (what arrived within a given wait). The base class owns
the counters and the "closed" state. ``batches`` is the one loop for reading a device until its
source ends.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import Counter
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

from ..core.calibration import Calibration, RecordState, StoredRecord
from ..core.errors import DeviceError, Unsupported
from ..core.events import Event, Identity, Item
from ..core.sample import Sample
from ..core.selftest import SelfTestResult


@dataclass(frozen=True)
class Abilities:
    """What a device can do beyond ``open``/``read``/``close``."""

    live: bool = True  # a device at the other end: takes commands, has data in flight (False: a recording)
    store: bool = True  # takes a calibration to keep: ``write_calibration``
    self_test: bool = False  # runs the AK8975 self-test: ``self_test()``


RECORDING = Abilities(live=False, store=False)


class Device(ABC):
    url: str = ""
    abilities: Abilities = Abilities()

    def __init__(self, url: str, clock: Callable[[], float] = time.monotonic):
        self.url = url
        self.clock = clock
        self.identity: Identity | None = None
        self.counters: Counter = Counter()
        self._closed = False

    # -- public surface --------------------------------------------------------------------
    def open(self) -> Identity:
        """Connect and identify; after ``close`` it connects again (a replug)."""
        self._closed = False
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
        deadline = self.clock() + max(0.0, timeout_s)
        while True:
            items = self._receive(deadline - self.clock())
            if items or self.clock() >= deadline:
                return list(items)

    def read_calibration(self) -> Calibration | None:
        """The calibration the device holds (a recording: the last one it showed), or None
        (nothing stored, or a record that cannot be used: ``read_stored`` says which)."""
        return self.read_stored().calibration

    def read_stored(self) -> StoredRecord:
        """What the device's store holds: a calibration, nothing, or a record that cannot be
        used (corrupt, or invalid contents behind a valid CRC) and why."""
        return self._read_stored()

    def discard_calibration(self) -> StoredRecord:
        """Leave nothing stored (after a write that did not verify, when there is nothing to put
        back); returns what the store holds afterwards."""
        self._require(self.abilities.store, "discard a calibration")
        return self._discard_calibration()

    def write_calibration(self, cal: Calibration) -> Calibration:
        """Store ``cal`` and return what the store holds afterwards (read back). The caller
        compares the two; a backend never claims success it has not read back."""
        self._require(self.abilities.store, "store a calibration")
        return self._write_calibration(cal)

    def prepare(self, cal: Calibration) -> Calibration:
        """``cal`` exactly as this device's store will hold it (fixed-point, float32 …)."""
        return cal

    def matches(self, sent: Calibration, stored: Calibration | None) -> bool:
        """Is ``stored`` (an echo or a read-back) the calibration that was sent?"""
        return stored is not None and sent.close_to(stored)

    def stored_in(self) -> str | None:
        """Where the calibration lives when that is a file on this host (else None: on the device)."""
        return None

    def self_test(self) -> SelfTestResult:
        """The AK8975 self-test (``abilities.self_test``)."""
        self._require(self.abilities.self_test, "run the AK8975 self-test")
        return self._self_test()

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

    def _require(self, ability: bool, what: str) -> None:
        if not ability:
            raise Unsupported(f"{self.url}: this source cannot {what}")

    # -- backend hooks ---------------------------------------------------------------------
    @abstractmethod
    def _open(self) -> Identity: ...

    @abstractmethod
    def _start(self, rate_hz: int | None) -> None: ...

    @abstractmethod
    def _stop(self) -> None: ...

    @abstractmethod
    def _receive(self, wait_s: float) -> Iterable[Item]:
        """What arrives within at most ``wait_s`` seconds (≤ 0: only what is there already);
        it may return early, with items or without."""

    def _read_calibration(self) -> Calibration | None:
        raise DeviceError(f"{self.url}: this backend cannot store a calibration")

    def _read_stored(self) -> StoredRecord:
        cal = self._read_calibration()
        return StoredRecord(RecordState.NONE) if cal is None else StoredRecord(RecordState.OK, cal)

    def _discard_calibration(self) -> StoredRecord:
        raise Unsupported(f"{self.url}: this device cannot discard its stored calibration")

    def _write_calibration(self, cal: Calibration) -> Calibration:
        raise DeviceError(f"{self.url}: this backend cannot store a calibration")

    def _self_test(self) -> SelfTestResult:
        raise DeviceError(f"{self.url}: this backend has no self-test")

    @abstractmethod
    def _close(self) -> None: ...


def batches(device: Device, timeout_s: float = 0.1) -> Iterator[list[Item]]:
    """The one loop that reads a device: batch after batch (possibly empty) until its source
    ends (a recording's end). The caller stops when it has enough; device errors propagate."""
    while True:
        try:
            items = device.read(timeout_s)
        except EOFError:
            return
        yield items


def read_to_end(device: Device) -> list[Sample]:
    """Open a finite source and read it to the end: its samples, in order (events dropped)."""
    out: list[Sample] = []
    device.open()
    try:
        for items in batches(device, 0.05):
            out.extend(i for i in items if isinstance(i, Sample))
    finally:
        device.close()
    return out


__all__ = ["Abilities", "Device", "Event", "Identity", "Item", "RECORDING", "batches", "read_to_end"]
