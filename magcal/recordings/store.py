"""The host-side calibration store, for chips that have nowhere to keep a calibration.

The AK8975 has no offset registers, so a calibration for a chip on a bare I2C bus lives on the
host: one JSON file per physical device, named by ``device_key(identity)`` (transport, bus,
address and the three fuse-ROM ASA bytes, which differ from chip to chip).

File format (``version`` 1)::

    {"format": "magcal.calibration", "version": 1, "key": "...", "device": {...},
     "saved_at": "2026-01-01T00:00:00Z", "calibration": {...Calibration.to_dict()},
     "sha256": "<hex digest of the canonical JSON of every other field>"}

Writes are atomic (``magcal.recordings.atomic.write_atomic``) and read back and compared; a file whose
checksum, format or version does not check out raises ``CorruptCalibrationFile`` naming the
file and the problem — it is never applied. The directory is ``$MAGCAL_STORE_DIR`` or
``~/.local/share/magcal/calibrations``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..core.calibration import Calibration, RecordState, StoredRecord
from ..core.errors import StateError, WriteRejected
from ..core.events import Identity
from ..core.sense import record_problem
from .atomic import write_atomic

FORMAT = "magcal.calibration"
VERSION = 1
ENV_DIR = "MAGCAL_STORE_DIR"


class CorruptCalibrationFile(StateError):
    """A stored calibration that is torn, edited, or not a calibration file we can read."""


class InvalidCalibrationFile(CorruptCalibrationFile):
    """A store file whose checksum holds but whose calibration is none (a matrix that is not
    positive definite, a field that is not positive …)."""


def default_dir() -> Path:
    env = os.environ.get(ENV_DIR)
    if env:
        return Path(env).expanduser()
    return Path.home() / ".local" / "share" / "magcal" / "calibrations"


def device_key(identity: Identity) -> str:
    """A file-name-safe key for the physical device behind ``identity``.

    Uses the transport, the bus and address when the backend reports them
    (``identity.extra["bus"]``, ``["address"]``), otherwise the firmware string, and always
    the ASA bytes (the per-chip fuse-ROM trim, so swapping the chip changes the key).
    """
    parts = [identity.transport]
    extra = identity.extra or {}
    if "bus" in extra:
        parts.append(str(extra["bus"]).removeprefix("/dev/"))
    if "address" in extra:
        addr = extra["address"]
        parts.append(f"0x{addr:02x}" if isinstance(addr, int) else str(addr).lower())
    if "bus" not in extra and identity.firmware:
        parts.append(identity.firmware)
    parts.append("asa" + "".join(f"{int(a):02x}" for a in identity.asa))
    key = "_".join(re.sub(r"[^A-Za-z0-9.+-]+", "-", p) for p in parts)
    key = key.strip("-._")
    return key or "device"


def _digest(body: dict) -> str:
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(canon.encode("ascii")).hexdigest()


@dataclass(frozen=True)
class StoredCalibration:
    """What a store file holds: the calibration and where/when it was saved."""

    calibration: Calibration
    path: Path
    key: str
    saved_at: str
    device: dict

    def to_dict(self) -> dict:
        return {
            "key": self.key,
            "path": str(self.path),
            "saved_at": self.saved_at,
            "device": self.device,
            "calibration": self.calibration.to_dict(),
        }


def _utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


class CalibrationStore:
    """One directory of calibration files, one per device identity."""

    def __init__(self, directory: str | os.PathLike | None = None, now: Callable[[], str] = _utc_now):
        self.directory = Path(directory).expanduser() if directory is not None else default_dir()
        self._now = now

    def path_for(self, identity: Identity) -> Path:
        return self.directory / f"{device_key(identity)}.json"

    # -- reading ---------------------------------------------------------------------------
    def load_record(self, identity: Identity) -> StoredCalibration | None:
        """The stored record for ``identity``; None when nothing was ever stored."""
        path = self.path_for(identity)
        try:
            text = path.read_bytes()
        except FileNotFoundError:
            return None
        return parse(text, path)

    def load(self, identity: Identity) -> Calibration | None:
        rec = self.load_record(identity)
        return None if rec is None else rec.calibration

    def stored(self, identity: Identity) -> StoredRecord:
        """What is stored for ``identity``: the calibration, nothing, or a file that cannot be
        used (corrupt: torn, edited, foreign; invalid: its checksum holds but it is no
        calibration) and why — never raised, never applied."""
        try:
            cal = self.load(identity)
        except CorruptCalibrationFile as exc:
            state = RecordState.INVALID if isinstance(exc, InvalidCalibrationFile) else RecordState.CORRUPT
            return StoredRecord(state, problem=str(exc))
        return StoredRecord(RecordState.NONE) if cal is None else StoredRecord(RecordState.OK, cal)

    def discard(self, identity: Identity) -> None:
        """Nothing stored for ``identity`` any more (its file removed)."""
        try:
            self.path_for(identity).unlink()
        except FileNotFoundError:
            pass

    # -- writing ---------------------------------------------------------------------------
    def save(self, identity: Identity, cal: Calibration) -> Calibration:
        """Store ``cal`` for ``identity`` atomically, read it back, compare; returns the
        calibration read back. Raises ``WriteRejected`` if the read-back differs."""
        path = self.path_for(identity)
        write_atomic(path, encode(identity, cal, saved_at=self._now()))
        back = self.load(identity)
        if back is None or not back.close_to(cal, atol_ut=1e-9, atol_w=1e-12):
            raise WriteRejected(f"{path}: the calibration read back differs from the one written")
        return back


def encode(identity: Identity, cal: Calibration, saved_at: str) -> bytes:
    """The bytes of a store file (pure: no clock, no file)."""
    body = {
        "format": FORMAT,
        "version": VERSION,
        "key": device_key(identity),
        "device": identity.to_dict(),
        "saved_at": saved_at,
        "calibration": cal.to_dict(),
    }
    body["sha256"] = _digest(body)
    return (json.dumps(body, indent=2, sort_keys=True) + "\n").encode("utf-8")


def parse(data: bytes, path: Path | str = "<calibration file>") -> StoredCalibration:
    """Check and decode a store file's bytes; raises ``CorruptCalibrationFile``."""
    where = str(path)
    try:
        body = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptCalibrationFile(f"{where}: not valid JSON ({exc}); the file is torn or edited, not applied") from None
    except RecursionError:
        raise CorruptCalibrationFile(f"{where}: JSON nested too deeply: not a calibration file, not applied") from None
    if not isinstance(body, dict) or body.get("format") != FORMAT:
        raise CorruptCalibrationFile(f"{where}: not a magcal calibration file (format field missing or wrong)")
    version = body.get("version")
    if version != VERSION:
        raise CorruptCalibrationFile(
            f"{where}: calibration file version {version!r}; this magcal reads version {VERSION}"
        )
    stored_sum = body.pop("sha256", None)
    if stored_sum != _digest(body):
        raise CorruptCalibrationFile(f"{where}: checksum mismatch; the file is torn or was edited, not applied")
    try:
        cal = Calibration.from_dict(body["calibration"])
        device = dict(body.get("device", {}))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InvalidCalibrationFile(f"{where}: its checksum holds but its calibration is none ({exc}); "
                                     "not applied") from None
    nonsense = record_problem(cal)  # checksum and shape right, and still no physical calibration
    if nonsense:
        raise InvalidCalibrationFile(f"{where}: its checksum holds but {nonsense}; not applied")
    return StoredCalibration(calibration=cal, path=Path(path), key=str(body.get("key", "")),
                             saved_at=str(body.get("saved_at", "")), device=device)
