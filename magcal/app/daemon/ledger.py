"""The write-ahead ledger of EEPROM writes: the daemon's write budget survives kill -9.

Every command that makes the device write its EEPROM (a calibration, the previous one put
back, a failed record erased) is first recorded here as an *intent* — one JSON line appended
to ``writes.jsonl`` in the state directory and fsynced — and only then sent. When the write
has been read back, the operation is *resolved* (another line: verified or not). A process
killed between the two leaves an unresolved intent; at the next start it counts as spent, since
the command may have reached the EEPROM. The budget (``logic.keeper.Keeper``) is charged from
this file, not from the state file, so no kill at any moment lets a write go uncounted.

Lines::

    {"op": 3, "intent": "write", "t_utc": 1800000000.0}        before each EEPROM command
    {"op": 3, "resolved": "verified", "t_utc": 1800000000.4}   after the read-back (or
                                                                "not_verified", "interrupted")

A line that cannot be read (a torn append) counts as one write spent at the time it is read.
The file is opened without following a link (``O_NOFOLLOW``), appended to only.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ...core.errors import DeviceError, StateError
from ...recordings.atomic import fsync_dir

LEDGER_NAME = "writes.jsonl"
VERIFIED, NOT_VERIFIED, INTERRUPTED = "verified", "not_verified", "interrupted"
WRITE, RESTORE, ERASE = "write", "restore", "erase"


class LedgerError(DeviceError):
    """The intent could not be made durable: the write command is not sent."""


@dataclass
class History:
    """What the ledger holds: the time of every EEPROM command (each one cycle), and the
    operations verified, not verified, and left unresolved by a process that was killed."""

    spent_at_s: list[float] = field(default_factory=list)
    verified: int = 0
    not_verified: int = 0
    unresolved: list[int] = field(default_factory=list)
    last_op: int = 0

    @property
    def cycles(self) -> int:
        return len(self.spent_at_s)

    @property
    def failed(self) -> int:
        """Operations not verified, an unresolved one among them."""
        return self.not_verified + len(self.unresolved)

    def to_dict(self) -> dict:
        return {"eeprom_cycles": self.cycles, "writes": self.verified, "failed": self.failed,
                "unresolved": len(self.unresolved)}


def read_history(path: Path, now_s: float) -> History:
    """The ledger at ``path`` summed up (an empty history when there is none)."""
    try:
        text = path.read_bytes().decode("utf-8", errors="replace")
    except FileNotFoundError:
        return History()
    except OSError as exc:
        raise StateError(f"the write ledger {path} cannot be read: {exc}") from None
    h, outcome, ops = History(), {}, []
    for line in text.splitlines():
        entry = _entry(line)
        if entry is None:
            if line.strip():
                h.spent_at_s.append(now_s)  # torn: a write may have followed it
            continue
        op = entry["op"]
        h.last_op = max(h.last_op, op)
        if "intent" in entry:
            h.spent_at_s.append(entry["t_utc"])
            if op not in outcome:
                ops.append(op)
                outcome[op] = None
        elif op in outcome:
            outcome[op] = entry["resolved"]
    for op in ops:
        if outcome[op] == VERIFIED:
            h.verified += 1
        elif outcome[op] is None:
            h.unresolved.append(op)
        else:
            h.not_verified += 1
    return h


def _entry(line: str) -> dict | None:
    """One well-formed ledger line, or None."""
    try:
        e = json.loads(line)
    except ValueError:
        return None
    if not isinstance(e, dict) or not isinstance(e.get("op"), int) or not isinstance(e.get("t_utc"), (int, float)):
        return None
    if not (isinstance(e.get("intent"), str) or isinstance(e.get("resolved"), str)):
        return None
    return e if e["t_utc"] == e["t_utc"] else None  # NaN is no time


class WriteLedger:
    """``writes.jsonl`` in ``state_dir``, appended to with an fsync per line."""

    def __init__(self, state_dir: Path, wall: Callable[[], float]):
        self.path = Path(state_dir) / LEDGER_NAME
        self._wall = wall
        self._fd: int | None = None
        self.history = History()

    def open(self) -> History:
        """Read what is there, resolve what a killed process left unresolved (as spent), and
        open for appending. The history read."""
        self.history = read_history(self.path, self._wall())
        flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
        try:
            created = not self.path.exists()
            self._fd = os.open(self.path, flags, 0o644)
            if created:
                fsync_dir(self.path.parent)
        except OSError as exc:
            raise StateError(f"the write ledger {self.path} cannot be opened: {exc}") from None
        for op in self.history.unresolved:
            self._append({"op": op, "resolved": INTERRUPTED})
        return self.history

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def begin(self) -> int:
        """A new operation's number."""
        self.history.last_op += 1
        return self.history.last_op

    def intent(self, op: int, what: str) -> None:
        """Durable before the command is sent (``LedgerError`` when it cannot be)."""
        t = self._wall()
        try:
            self._append({"op": op, "intent": what})
        except (OSError, StateError) as exc:
            raise LedgerError(f"not written: the write ledger cannot record the intent: {exc}") from None
        self.history.spent_at_s.append(t)

    def resolve(self, op: int, verified: bool) -> None:
        """After the read-back. Losing this line costs nothing but a write counted as failed."""
        try:
            self._append({"op": op, "resolved": VERIFIED if verified else NOT_VERIFIED})
        except (OSError, StateError):
            self.history.unresolved.append(op)
            return
        if verified:
            self.history.verified += 1
        else:
            self.history.not_verified += 1

    def _append(self, entry: dict) -> None:
        if self._fd is None:
            raise StateError("the write ledger is not open")
        line = json.dumps({**entry, "t_utc": round(self._wall(), 3)}, separators=(",", ":")) + "\n"
        os.write(self._fd, line.encode())
        os.fsync(self._fd)


class LedgeredDevice:
    """A device whose every EEPROM command is recorded in the ledger first (one operation);
    everything else goes straight to the device."""

    def __init__(self, device, ledger: WriteLedger):
        self._device = device
        self._ledger = ledger
        self.op = ledger.begin()
        self.commands = 0

    def __getattr__(self, name):
        return getattr(self._device, name)

    def write_calibration(self, cal):
        self._ledger.intent(self.op, RESTORE if self.commands else WRITE)
        self.commands += 1
        return self._device.write_calibration(cal)

    def discard_calibration(self):
        self._ledger.intent(self.op, ERASE)
        self.commands += 1
        return self._device.discard_calibration()

    def resolve(self, verified: bool) -> int:
        """The operation is over; the EEPROM commands it sent (recorded)."""
        if self.commands:
            self._ledger.resolve(self.op, verified)
        return self.commands
