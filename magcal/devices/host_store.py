"""A host-side calibration store any backend can wear: for a chip that keeps no calibration of
its own (the AK8975 has no offset registers), the calibration lives in a file on this host,
one per device identity (``magcal.recordings.store.CalibrationStore``).

A backend wears it by listing ``HostStore`` before ``Device`` among its bases and setting
``store_dir`` (None: the store's default directory); it must provide ``identity`` (set by
``open``) and ``_require_open`` (a ``DeviceError`` before open or after close).
"""

from __future__ import annotations

from ..core.calibration import Calibration, StoredRecord


class HostStore:
    """Reading, writing and discarding a device's calibration in the host-side store."""

    store_dir = None  # the wearer's store directory; None: the store's default

    def _store(self):
        from ..recordings.store import CalibrationStore

        return CalibrationStore(self.store_dir)

    @property
    def store_path(self):
        """The store file that holds (or will hold) this device's calibration; None before open."""
        return None if self.identity is None else self._store().path_for(self.identity)

    def stored_in(self) -> str | None:
        return None if self.store_path is None else str(self.store_path)

    def _read_stored(self) -> StoredRecord:
        self._require_open()
        return self._store().stored(self.identity)

    def _discard_calibration(self) -> StoredRecord:
        self._require_open()
        self._store().discard(self.identity)
        return self._store().stored(self.identity)

    def _write_calibration(self, cal: Calibration) -> Calibration:
        self._require_open()
        return self._store().save(self.identity, cal)
