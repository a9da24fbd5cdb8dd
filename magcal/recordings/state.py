"""The daemon's state file: versioned JSON with a checksum, replaced atomically.

On disk (one JSON object, UTF-8)::

    {"format": "magcal-state", "version": 1, "sha256": "<hex of the canonical payload>",
     "payload": {...}}

The checksum covers the payload serialised canonically (sorted keys, no spaces), so a file cut
short, edited by hand or mixed from two writes is refused with ``StateError`` rather than read
as valid. ``StateFiles.save`` keeps the previous good file as ``state.prev.json`` before it
replaces ``state.json`` (both through ``magcal.recordings.atomic.write_atomic``: write, fsync, rename,
fsync the directory); ``StateFiles.load`` falls back to the previous file when the current one
is invalid, and says so.

Nothing here knows what the payload means: the daemon decides that (see ``magcal.app.daemon``).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from ..core.errors import ConfigError, StateError
from .atomic import write_atomic

FORMAT = "magcal-state"
VERSION = 1
CURRENT = "state.json"
PREVIOUS = "state.prev.json"


def _canonical(payload: dict) -> bytes:
    try:
        return json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise StateError(f"state payload is not JSON-serialisable: {exc}") from None


def encode_state(payload: dict) -> bytes:
    """The bytes of a state file holding ``payload`` (a JSON-able dict)."""
    if not isinstance(payload, dict):
        raise StateError(f"state payload must be a dict, not {type(payload).__name__}")
    body = _canonical(payload)
    digest = hashlib.sha256(body).hexdigest()
    head = json.dumps({"format": FORMAT, "version": VERSION, "sha256": digest}, separators=(",", ":"))
    # '{"format":…,"sha256":"…","payload":<canonical body>}\n' — the body appears verbatim.
    return head[:-1].encode("utf-8") + b',"payload":' + body + b"}\n"


def decode_state(data: bytes, name: str = "state file") -> dict:
    """The payload of a state file; ``StateError`` naming the defect when it is not valid."""
    if not data:
        raise StateError(f"{name} is empty")
    try:
        doc = json.loads(data.decode("utf-8"), parse_constant=_refuse_constant)
    except (UnicodeDecodeError, ValueError) as exc:
        raise StateError(f"{name} is not valid JSON (torn or corrupted): {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise StateError(f"{name} is not a magcal state file (format must be {FORMAT!r})")
    if doc.get("version") != VERSION:
        raise StateError(f"{name} has state version {doc.get('version')!r}; this magcal reads version {VERSION}")
    payload = doc.get("payload")
    if not isinstance(payload, dict):
        raise StateError(f"{name} has no payload object")
    digest = hashlib.sha256(_canonical(payload)).hexdigest()
    if doc.get("sha256") != digest:
        raise StateError(f"{name} fails its checksum (the payload was altered or mixed)")
    return payload


def _refuse_constant(token: str):
    raise ValueError(f"non-finite number {token} in state file")


def user_state_dir() -> Path:
    """The user's state directory for magcal (XDG base directories): ``$XDG_STATE_HOME/magcal``,
    else ``~/.local/state/magcal``."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "magcal"


def board_eeprom(given: str | None, kind: str, name: str) -> str | None:
    """The EEPROM file a simulated or emulated board keeps: ``given`` (a port's ``eeprom=``) when
    set, None (a throwaway store) for ``none``, else ``name`` in the user's state directory under
    ``kind`` (``sim``, ``emu``), created, so what one command wrote the next one reads."""
    if given == "none":
        return None
    if given:
        return given
    folder = user_state_dir() / kind
    folder.mkdir(parents=True, exist_ok=True)
    return str(folder / name)


def chip_suffix(chip) -> str:
    """The part of a board's EEPROM file name that tells a chip other than the MPU-9150 apart."""
    return "" if chip is None or chip.name == "mpu9150" else f"-{chip.name}-{chip.bits}bit"


def state_directory(path, create: bool = True) -> Path:
    """The daemon's state directory (empty: the user's, ``user_state_dir``), checked before
    anything is put in it: ConfigError naming the path and the fix when it is a file, cannot be
    created or cannot be written. Created (with its parents) when ``create``; new directories get
    the process umask's permissions."""
    d = Path(os.path.expanduser(os.fspath(path))) if os.fspath(path) else user_state_dir()
    what = f"state directory {d}"
    try:
        existing = next((p for p in (d, *d.parents) if p.exists()), None)
    except OSError as exc:  # a parent this user may not look into
        raise ConfigError(f"{what}: cannot be looked at: {exc.strerror or exc} (give --state-dir a directory "
                          "this user may use)") from None
    if existing is not None and not existing.is_dir():
        where = "is a file" if existing == d else f"is inside {existing}, which is a file"
        raise ConfigError(f"{what}: {where}, not a directory (give --state-dir a directory)")
    if not create:
        return d
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{what}: cannot be created: {exc.strerror or exc} (give --state-dir a directory "
                          "this user may create or write)") from None
    if not os.access(d, os.W_OK | os.X_OK, effective_ids=os.access in os.supports_effective_ids):
        raise ConfigError(f"{what}: not writable by this user (uid {os.geteuid()}); give --state-dir a "
                          "directory it may write")
    return d


class StateFiles:
    """``state.json`` and ``state.prev.json`` in one directory."""

    def __init__(self, directory):
        self.directory = Path(directory).expanduser()
        self.current = self.directory / CURRENT
        self.previous = self.directory / PREVIOUS
        self.last_load_note = ""  # what load() had to do (fell back, found nothing …)
        self.loaded_from: str | None = None  # the file the last load() read (None: none was valid)
        self._valid_digest: bytes | None = None  # SHA-256 of the last state.json bytes known valid

    def _known_valid(self, data: bytes) -> bool:
        """Are these the very bytes this object last wrote or read as a valid ``state.json``?"""
        return self._valid_digest is not None and hashlib.sha256(data).digest() == self._valid_digest

    def save(self, payload: dict) -> None:
        """Keep the current good file as the previous one, then replace the current one.
        Raises ``OSError`` when the directory cannot be written (the old files stay)."""
        data = encode_state(payload)
        try:
            old = self.current.read_bytes()
        except FileNotFoundError:
            old = None
        if old is not None and not self._known_valid(old):  # the daemon's own last save: checked when made
            try:
                decode_state(old)
            except StateError:
                old = None  # never promote a bad file to "previous good"
        if old is not None:
            write_atomic(self.previous, old)
        write_atomic(self.current, data)
        self._valid_digest = hashlib.sha256(data).digest()

    def load(self) -> dict | None:
        """The newest valid payload; None when there is no state at all.

        Falls back to the previous file when the current one is torn or invalid; raises
        ``StateError`` (naming both defects) when state exists but neither file is valid."""
        errors = []
        self.loaded_from = None
        for path in (self.current, self.previous):
            try:
                data = path.read_bytes()
            except FileNotFoundError:
                continue
            except OSError as exc:
                errors.append(f"{path}: cannot read: {exc.strerror or exc}")
                continue
            try:
                payload = decode_state(data, path.name)
            except StateError as exc:
                errors.append(str(exc))
                continue
            self.last_load_note = (
                f"loaded {path.name}" + (f" after refusing {self.current.name}: {errors[0]}" if errors else "")
            )
            self.loaded_from = path.name
            if path == self.current:
                self._valid_digest = hashlib.sha256(data).digest()
            return payload
        if errors:
            raise StateError("no valid state: " + "; ".join(errors))
        self.last_load_note = "no state yet"
        return None
