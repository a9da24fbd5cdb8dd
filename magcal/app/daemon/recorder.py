"""The daemon's rolling capture: every byte the link reads, kept in the state directory within a
bound (``daemon.capture_max_bytes``: two files of half the bound each, ``capture.cap`` and
``capture.cap.1``), so the last stretch of a session can be replayed. A capture that fails (a
full disk) stops; streaming goes on."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from ...recordings.capture import CaptureWriteError, CaptureWriter, make_header, roll_keep_one
from .journal import Decision, Journal

CAPTURE_NAME = "capture.cap"


class RollingCapture:
    def __init__(self, state_dir: Path, journal: Journal, faults: Counter):
        self.path = Path(state_dir) / CAPTURE_NAME
        self._journal = journal
        self._faults = faults
        self.writer: CaptureWriter | None = None

    def open(self, settings) -> None:
        limit = settings.daemon.capture_max_bytes
        if not limit:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            header = make_header(settings.port, settings.baud, settings.dialect)
            self.writer = CaptureWriter(self.path, header, max_bytes=max(4096, limit // 2), on_full=roll_keep_one)
        except (CaptureWriteError, OSError, ValueError) as exc:
            self._faults["capture_failed"] += 1
            self._journal.record(Decision.CAPTURE_NOT_STARTED, error=str(exc))
            self.writer = None
            return
        self._journal.record(Decision.CAPTURE_ROLLING, path=str(self.path), max_bytes=limit)

    def failed(self, exc: CaptureWriteError) -> None:
        self._faults["capture_failed"] += 1
        self._journal.record(Decision.CAPTURE_STOPPED, error=str(exc))

    def stats(self) -> dict | None:
        return None if self.writer is None else self.writer.stats()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
