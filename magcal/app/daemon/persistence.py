"""The state keeper: what the daemon writes so that a restart resumes where it stopped, and the
lock that keeps one daemon per state directory.

The file (``magcal.recordings.state.StateFiles``: atomic, checksummed, previous good file kept)
holds one payload: ``{"kind", "generation", "saved_utc", "status", "resume"}``. ``resume`` is
read back by ``Saved.parse`` into typed values before any of it is used, so a state that is
malformed anywhere is refused whole.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ...core.calibration import Calibration
from ...core.errors import StateError
from ...logic.monitor import DriftMonitor
from ...logic.session import Session
from ...recordings.state import StateFiles
from .journal import Decision, Journal

STATE_KIND = "magcal-daemon"


@dataclass
class Saved:
    """The ``resume`` part of a state file, as typed values."""

    generation: int
    port: str | None
    samples: int
    samples_in: int
    epoch: int
    recalibrations: int
    replay_lines: int
    faults: Counter
    session: Session
    monitor: DriftMonitor | None
    calibration: Calibration | None
    last_calibration: dict | None
    decisions: list = field(default_factory=list)

    @classmethod
    def parse(cls, data: dict, gates) -> "Saved":
        """KeyError, TypeError or ValueError when anything in it is malformed."""
        if data.get("kind") != STATE_KIND:
            raise ValueError(f"state kind is {data.get('kind')!r}, not {STATE_KIND!r}")
        r = data["resume"]
        return cls(
            generation=int(data["generation"]),
            port=r.get("port"),
            samples=int(r["samples"]),
            samples_in=int(r["samples_in"]),
            epoch=int(r["epoch"]),
            recalibrations=int(r["recalibrations"]),
            replay_lines=int(r.get("replay_lines", 0)),
            faults=Counter({str(k): int(v) for k, v in r["faults"].items()}),
            session=Session.from_state(r["session"], gates),
            monitor=DriftMonitor.from_state(r["monitor"]) if r["monitor"] else None,
            calibration=Calibration.from_dict(r["calibration"]) if r["calibration"] else None,
            last_calibration=r.get("last_calibration"),
            decisions=list(r.get("decisions", [])),
        )

    def counters_only(self, session: Session) -> "Saved":
        """Another device's state: its counters go on, its samples and calibrations do not."""
        return Saved(self.generation, self.port, self.samples, self.samples_in, self.epoch, self.recalibrations,
                     0, self.faults, session, None, None, None, self.decisions)


def why_unusable(exc: Exception) -> str:
    """Why a state file whose checksum holds cannot be resumed, in words (a KeyError's own text
    is only the key: ``'resume'``)."""
    if isinstance(exc, KeyError):
        return f"the state file has no {exc.args[0]!r} entry where one is needed (written by another program?)"
    return f"the state file's content is malformed: {exc}"


class StateKeeper:
    def __init__(self, state_dir: Path, journal: Journal, faults: Counter,
                 clock: Callable[[], float] = time.monotonic):
        self.files = StateFiles(state_dir)
        self._journal = journal
        self._faults = faults
        self._clock = clock
        self.generation = 0
        self._next_save = 0.0

    def due(self, now: float) -> bool:
        return now >= self._next_save

    def save(self, payload: Callable[[int], dict], every_s: float) -> bool:
        """Write ``payload(generation)``; the next save is due ``every_s`` from now."""
        self._next_save = self._clock() + every_s
        self.generation += 1
        try:
            self.files.save(payload(self.generation))
        except (OSError, StateError) as exc:
            self._faults["state_write_failed"] += 1
            self._journal.record(Decision.STATE_NOT_WRITTEN, error=str(exc))
            return False
        return True

    def load(self) -> dict | None:
        """The saved payload; None (and why, in the journal) when there is none to resume."""
        try:
            data = self.files.load()
        except StateError as exc:
            self._faults["state_refused"] += 1
            self._journal.record(Decision.STATE_REFUSED, error=str(exc))
            return None
        if data is None:
            self._journal.record(Decision.NO_STATE)
        return data

    def restore(self, generation: int) -> None:
        """Resumed: the next save goes on from the saved generation."""
        self.generation = generation

    @property
    def load_note(self) -> str:
        """What the last load had to do, in words (fell back, found nothing …)."""
        return self.files.last_load_note

    @property
    def loaded_from(self) -> str | None:
        """The file the last load took its state from (``state.prev.json`` after a fall-back)."""
        return self.files.loaded_from


class StateDirLock:
    """An exclusive lock on ``state_dir/lock`` for a daemon's lifetime (released by the kernel
    even after kill -9): two daemons must never write one state."""

    def __init__(self, state_dir: Path):
        self.state_dir = state_dir
        self._fd: int | None = None

    def __enter__(self) -> "StateDirLock":
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            return self
        self.state_dir.mkdir(parents=True, exist_ok=True)
        try:  # never through a link planted in its place (O_NOFOLLOW)
            fd = os.open(self.state_dir / "lock", os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as exc:
            raise StateError(f"cannot take the lock {self.state_dir / 'lock'}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise StateError(f"another magcal daemon is running on {self.state_dir}") from None
        self._fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
