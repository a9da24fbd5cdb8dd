"""What ``magcal fleet`` reads: folders (walked), globs, and manifests (CSV with the columns
``path``, ``vehicle`` and optionally ``notes``; paths relative to the manifest's folder).

In a folder, a file is taken when its content is a flight log or a magcal capture, or its name
ends like a table (.csv, .tsv, .txt); anything else there (notes, pictures) is left alone. A file
named on the command line is always taken: one that cannot be read becomes a row with its error.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import os
from dataclasses import dataclass

from ...core.errors import InputError

TABLE_SUFFIXES = (".csv", ".tsv", ".txt")
HASH_BLOCK = 1 << 20


@dataclass(frozen=True)
class Source:
    """One file to analyse and what the command line says of it (the log's own vehicle id wins)."""

    path: str
    vehicle: str  # from the manifest or the folder holding the file
    vehicle_from: str  # "manifest" | "folder"
    notes: str = ""

    def to_dict(self) -> dict:
        return {"path": self.path, "vehicle": self.vehicle, "vehicle_from": self.vehicle_from, "notes": self.notes}


def file_sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(HASH_BLOCK):
            h.update(block)
    return h.hexdigest()


def is_manifest(path: str) -> bool:
    """A CSV whose header names ``path`` and ``vehicle``."""
    if not path.lower().endswith(".csv") or not os.path.isfile(path):
        return False
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        header = next(csv.reader(fh), [])
    names = {h.strip().lower() for h in header}
    return {"path", "vehicle"} <= names


def read_manifest(path: str) -> list[Source]:
    base = os.path.dirname(os.path.abspath(path))
    out = []
    with open(path, newline="", encoding="utf-8") as fh:
        for line, row in enumerate(csv.DictReader(fh), start=2):
            row = {(k or "").strip().lower(): (v or "").strip() for k, v in row.items()}
            if not row.get("path") or not row.get("vehicle"):
                raise InputError(f"{path} line {line}: a manifest row needs a path and a vehicle")
            p = row["path"] if os.path.isabs(row["path"]) else os.path.join(base, row["path"])
            out.append(Source(os.path.normpath(p), row["vehicle"], "manifest", row.get("notes", "")))
    return out


def _wanted_in_folder(path: str) -> bool:
    from ...recordings.capture import MAX_HEADER, is_capture
    from ...recordings.logs import HEAD_BYTES, log_kind

    if path.lower().endswith(TABLE_SUFFIXES):
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER)
    except OSError:
        return False
    return log_kind(head[:HEAD_BYTES]) is not None or is_capture(head)


def _from_file(path: str) -> Source:
    parent = os.path.basename(os.path.dirname(os.path.abspath(path)))
    return Source(os.path.normpath(path), parent, "folder")


def _walk(folder: str) -> list[Source]:
    out = []
    for dirpath, dirnames, files in os.walk(folder):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for f in sorted(files):
            p = os.path.join(dirpath, f)
            if not f.startswith(".") and not is_manifest(p) and _wanted_in_folder(p):
                out.append(_from_file(p))
    return out


def expand(specs: list[str]) -> list[Source]:
    """Every file the SOURCES name, each once (the first mention wins), in a stable order."""
    found: list[Source] = []
    for spec in specs:
        if os.path.isdir(spec):
            found += _walk(spec)
        elif is_manifest(spec):
            found += read_manifest(spec)
        elif os.path.isfile(spec):
            found.append(_from_file(spec))
        else:
            hits = sorted(glob.glob(spec, recursive=True))
            if not hits:
                raise InputError(f"{spec}: no such file, folder or manifest, and no file matches it as a glob")
            found += [s for h in hits for s in (_walk(h) if os.path.isdir(h) else [_from_file(h)])]
    seen, out = set(), []
    for s in found:
        if s.path not in seen:
            seen.add(s.path)
            out.append(s)
    return out
