"""Captures (the raw bytes a device sent, with receive times), and
``load_series``: any recording file → ``Series``.

Capture file format, version 1
------------------------------
One header line of UTF-8 JSON, then binary chunks until the end of the file::

    {"format": "magcal-capture", "version": 1, "port": "...", "baud": 115200,
     "start_utc": "2026-11-22T05:00:00.000000+00:00", "tool": "magcal 0.1.0",
     "dialect": "native"}\\n
    chunk*

    chunk = b"K" | t_rx (float64 LE, seconds since the start of the recording)
                 | n (uint32 LE) | n bytes exactly as read from the port

The header names where the bytes came from; nothing in it is needed to parse them. A chunk is
appended whole with one ``write`` and the file is flushed often (``flush_interval_s``), so a
capture is readable after a crash mid-write: a truncated last chunk is ignored and reported
(``CaptureReader.truncated_bytes``), never fatal. A bad chunk marker in the middle ends the
readable part the same way (reported, with its offset).

Replaying a capture feeds the same bytes through the same parser as the live link, so it
reproduces the same samples; ``load_series`` uses the bulk parser (``magcal.wire.bulk``),
which gives the same result as the incremental one (tests hold the two together). A capture
is read block by block (``CaptureReader.frames``): memory beyond the samples stays bounded by
``BLOCK_BYTES`` however long the recording, and the counts are those of one whole pass.

Writing: ``CaptureWriter`` appends chunks; ``writer.tap(transport)`` (or ``writer(transport)``)
wraps a pyserial-like transport so that every byte read is also recorded. ``max_bytes`` bounds
the file: when the next chunk would cross it, ``on_full(writer)`` may return a path to continue
in (``roll_keep_one`` keeps one previous file), otherwise recording stops (``writer.full``) and
further bytes are only counted. A failed write (disk full, I/O error) stops recording and raises
``CaptureWriteError`` once, from the *next* read of the tap, after the bytes of the failed chunk
have already been handed to the caller — so what the device sent is never lost and the caller
can keep streaming.

Tables (magcal's CSV and other people's delimited text) are read by ``magcal.recordings.table``;
``load_series`` tells the kinds of recording apart by their content.
"""

from __future__ import annotations

import json
import math
import mmap
import os
import struct
import time
from array import array
from datetime import datetime, timezone
from typing import Callable, Iterator

import numpy as np

from .. import __version__
from ..core.errors import InputError, MagcalError
from ..wire.bulk import Frames, parse_blocks
from ..wire.dialect import Dialect, dialect_of
from .frames_series import series_from_frames  # noqa: F401  (read with the capture: the loaders' import)

FORMAT = "magcal-capture"
VERSION = 1
CHUNK_MARK = b"K"
_CHUNK_HEAD = struct.Struct("<dI")
CHUNK_OVERHEAD = 1 + _CHUNK_HEAD.size  # 13 bytes per chunk
MAX_HEADER = 64 * 1024
BLOCK_BYTES = 1 << 22  # how much of a capture file is read (or held) at once
_RELEASE = getattr(mmap, "MADV_DONTNEED", None)  # let go of mapped pages already read


class CaptureWriteError(MagcalError):
    """Recording stopped because the capture file could not be written (disk full, I/O error).
    The bytes of the failed chunk were delivered to the caller; the file holds everything
    before them."""


def make_header(port: str, baud: int | None = None, dialect: Dialect = Dialect.NATIVE,
                start_utc: datetime | None = None) -> dict:
    start = start_utc or datetime.now(timezone.utc)
    if str(port).startswith("replay://") and dialect is Dialect.NATIVE:
        dialect = Dialect.AUTO  # a replay speaks its own capture's convention: read back from the bytes
    return {
        "format": FORMAT,
        "version": VERSION,
        "port": str(port),
        "baud": None if baud is None else int(baud),
        "start_utc": start.isoformat(timespec="microseconds"),
        "tool": f"magcal {__version__}",
        "dialect": dialect.value,
    }


def _header_line(header: dict) -> bytes:
    h = {"format": FORMAT, "version": VERSION, **header}
    return (json.dumps(h, ensure_ascii=True, sort_keys=False) + "\n").encode("ascii")


def roll_keep_one(writer: "CaptureWriter") -> str:
    """An ``on_full`` policy: the full file becomes ``PATH.1`` (replacing an older one) and
    recording continues in a fresh ``PATH``."""
    os.replace(writer.path, writer.path + ".1")
    return writer.path


class CaptureWriter:
    """Append-only capture file. See the module docstring for the format and failure rules."""

    def __init__(
        self,
        path,
        header: dict,
        max_bytes: int | None = None,
        on_full: Callable[["CaptureWriter"], str | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        flush_interval_s: float = 0.2,
    ):
        self.path = os.fspath(path)
        self.header = dict(header)
        self.max_bytes = max_bytes
        self.on_full = on_full
        self.flush_interval_s = flush_interval_s
        self._clock = clock
        self._t0 = clock()
        self._last_flush = self._t0
        self.chunks = 0  # chunks written (all files)
        self.bytes_recorded = 0  # payload bytes written (all files)
        self.dropped_bytes = 0  # payload bytes not written (full or failed)
        self.rolls = 0
        self.full = False
        self.error: CaptureWriteError | None = None
        self._pending_error: CaptureWriteError | None = None
        self._fh = None
        self._size = 0
        self._open_file(self.path)

    # -- file handling -----------------------------------------------------------------------
    def _open_file(self, path: str) -> None:
        line = _header_line(self.header)
        if self.max_bytes is not None and len(line) + CHUNK_OVERHEAD + 1 > self.max_bytes:
            raise ValueError(f"max_bytes={self.max_bytes} cannot hold even the capture header")
        try:
            # the named file, never a link planted in its place (O_NOFOLLOW)
            flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
            fh = os.fdopen(os.open(path, flags, 0o644), "wb")
            fh.write(line)
            fh.flush()
        except OSError as exc:
            raise CaptureWriteError(f"cannot start capture {path}: {exc.strerror or exc}") from exc
        self._fh = fh
        self._size = len(line)
        self.path = path

    def _fail(self, exc: OSError, n: int) -> None:
        good = self._size
        try:  # best effort: leave no half chunk behind
            self._fh.flush()
        except OSError:
            pass
        try:
            self._fh.truncate(good)
            self._fh.close()
        except OSError:
            pass
        self._fh = None
        what = "disk full" if getattr(exc, "errno", None) == 28 else (exc.strerror or str(exc))
        self.error = CaptureWriteError(
            f"capture {self.path}: {what}; recording stopped after {self.bytes_recorded} bytes "
            f"(the device's data is still delivered)"
        )
        self._pending_error = self.error
        self.dropped_bytes += n

    @property
    def recording(self) -> bool:
        return self._fh is not None and not self.full

    def append(self, data: bytes, t_rx_s: float | None = None) -> bool:
        """Record one chunk; True when written. Never raises for a full or failed file (see
        ``error``/``full``); the tap turns a failure into one CaptureWriteError."""
        data = bytes(data)
        if not data:
            return True
        if not self.recording:
            self.dropped_bytes += len(data)
            return False
        now = self._clock()
        t = (now - self._t0) if t_rx_s is None else float(t_rx_s)
        blob = CHUNK_MARK + _CHUNK_HEAD.pack(t, len(data)) + data
        if self.max_bytes is not None and self._size + len(blob) > self.max_bytes:
            if not self._roll():
                self.full = True
                self.dropped_bytes += len(data)
                return False
            if self._size + len(blob) > self.max_bytes:  # one chunk bigger than a whole file
                self.dropped_bytes += len(data)
                return False
        try:
            self._fh.write(blob)
            if now - self._last_flush >= self.flush_interval_s:
                self._fh.flush()
                self._last_flush = now
        except OSError as exc:
            self._fail(exc, len(data))
            return False
        self._size += len(blob)
        self.chunks += 1
        self.bytes_recorded += len(data)
        return True

    def _roll(self) -> bool:
        if self.on_full is None:
            return False
        self._fh.close()
        self._fh = None
        new_path = self.on_full(self)
        if not new_path:
            return False
        self._open_file(os.fspath(new_path))
        self.rolls += 1
        return True

    @property
    def failing(self) -> bool:
        """A failure is waiting to be reported (``take_error``)."""
        return self._pending_error is not None

    def take_error(self) -> CaptureWriteError | None:
        """The failure not yet reported, if any (reported once)."""
        e, self._pending_error = self._pending_error, None
        return e

    def flush(self) -> None:
        if self._fh is not None:
            try:
                self._fh.flush()
            except OSError as exc:
                self._fail(exc, 0)
            self._last_flush = self._clock()

    def close(self) -> None:
        if self._fh is not None:
            try:
                self._fh.flush()
                self._fh.close()
            except OSError as exc:
                self._fail(exc, 0)
            self._fh = None

    def stats(self) -> dict:
        return {
            "path": self.path,
            "chunks": self.chunks,
            "bytes": self.bytes_recorded,
            "dropped_bytes": self.dropped_bytes,
            "rolls": self.rolls,
            "full": self.full,
            "error": None if self.error is None else str(self.error),
        }

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_capture_tap(path, settings, max_bytes: int | None = None, on_full=None) -> CaptureWriter:
    """A writer whose header names ``settings.port``/``baud``/``dialect``; pass it as the
    device's ``tap`` option."""
    header = make_header(
        getattr(settings, "port", "?"), getattr(settings, "baud", None), getattr(settings, "dialect", Dialect.NATIVE)
    )
    return CaptureWriter(path, header, max_bytes=max_bytes, on_full=on_full)


# -- reading -------------------------------------------------------------------------------
def is_capture(head: bytes) -> bool:
    """True when ``head`` (the first bytes of a file) starts a magcal capture."""
    line = head.split(b"\n", 1)[0]
    if not line.startswith(b"{"):
        return False
    try:
        return json.loads(line.decode("utf-8")).get("format") == FORMAT
    except (ValueError, AttributeError, RecursionError):
        return False


def _read_header(blob: bytes, path: str) -> tuple[dict, int]:
    nl = blob.find(b"\n", 0, MAX_HEADER)
    if nl < 0 or not is_capture(blob[: nl + 1]):
        more = " (or its header line is longer than 64 KiB)" if blob[:1] == b"{" and nl < 0 else ""
        raise InputError(f"{path} line 1: not a magcal capture (no capture header){more}")
    try:
        header = json.loads(blob[:nl].decode("utf-8"))
    except (ValueError, RecursionError):
        raise InputError(f"{path} line 1: the capture header is not a JSON object") from None
    if header.get("version") != VERSION:
        raise InputError(f"{path} line 1: capture version {_short(header.get('version'))} is not {VERSION}")
    return header, nl + 1


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "…"


MAX_PAUSE_S = 1e7  # receive times of two chunks in a row never differ by more (116 days)


def _header_at(blob: bytes, i: int, last_t: float, marker: bool = True) -> tuple[float, int] | None:
    """(time, end) of a chunk at ``i`` whose header checks out — the marker (unless ``marker``
    is False), a finite receive time from ``last_t`` to MAX_PAUSE_S after it, a size within
    the file — else None."""
    if i + CHUNK_OVERHEAD > len(blob) or (marker and blob[i : i + 1] != CHUNK_MARK):
        return None
    t, size = _CHUNK_HEAD.unpack_from(blob, i + 1)
    end = i + CHUNK_OVERHEAD + size
    if not (math.isfinite(t) and (last_t == -math.inf or last_t <= t <= last_t + MAX_PAUSE_S)) or end > len(blob):
        return None
    return t, end


def _next_ok(blob: bytes, end: int, t: float, strict: bool) -> bool:
    """Can what follows a chunk that ends at ``end`` (received at ``t``) be read on? The end of
    the file, or a marker — ``strict``: with a header that checks out, or cut short by the end
    of the file; not ``strict``: a header that checks out without its marker is enough (that
    chunk's marker byte is then the damage)."""
    if end >= len(blob):
        return True
    if blob[end : end + 1] == CHUNK_MARK:
        return not strict or _header_at(blob, end, t) is not None or _cut_short(blob, end)
    return not strict and _header_at(blob, end, t, marker=False) is not None


def _resync(blob: bytes, i: int, last_t: float) -> tuple[int, float, int] | None:
    """After damage at ``i``: (start, time, end) of the next chunk that checks out together with
    the one after it — the chunk at ``i`` itself when only its marker byte is wrong. None when
    nothing after ``i`` does."""
    h = _header_at(blob, i, last_t, marker=False)
    if h is not None and _next_ok(blob, h[1], h[0], strict=True):
        return i, h[0], h[1]
    j = blob.find(CHUNK_MARK, i + 1)
    while j >= 0:
        h = _header_at(blob, j, last_t)
        if h is not None and _next_ok(blob, h[1], h[0], strict=True):
            return j, h[0], h[1]
        j = blob.find(CHUNK_MARK, j + 1)
    return None


def _cut_short(blob: bytes, i: int) -> bool:
    """Is the chunk at ``i`` the last one, cut short by the end of the file (a crash mid-write)?"""
    if blob[i : i + 1] != CHUNK_MARK:
        return False
    if i + CHUNK_OVERHEAD > len(blob):
        return True
    return i + CHUNK_OVERHEAD + _CHUNK_HEAD.unpack_from(blob, i + 1)[1] > len(blob)


class CaptureReader:
    """A capture file: ``header`` (dict), iteration yields ``(t_rx_s, bytes)`` per chunk.

    Damage is read around and counted, never fatal: ``truncated_bytes`` > 0 when the file ends
    inside a chunk (a crash mid-write); ``damaged_chunks`` counts places where the chunk
    structure broke (a flipped marker, size or time byte) and ``skipped_bytes`` what was not
    read there. Reading resumes at the next place where two chunks in a row check out (marker,
    a finite receive time not earlier than the last, a size within the file); a chunk whose
    only defect is its marker byte is kept. ``problem`` says where the first damage was.

    Memory stays bounded by ``block_bytes`` beyond the chunk table (two numbers per chunk): the
    chunk structure is read through a memory map whose pages are released behind the reading
    position every ``block_bytes``, and the payload is read back in blocks of that size
    (``blocks``, ``frames``) — the whole file is never held."""

    def __init__(self, path, block_bytes: int = BLOCK_BYTES):
        self.path = os.fspath(path)
        self.block_bytes = max(1, int(block_bytes))
        self._blob: bytes | None = None
        try:
            with open(self.path, "rb") as fh:
                size = os.fstat(fh.fileno()).st_size
                if size <= self.block_bytes:
                    self._blob = fh.read()
                    self._parse(self._blob)
                else:
                    with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                        self._parse(mm)
        except OSError as exc:
            raise InputError(f"{self.path}: cannot read: {exc.strerror or exc}") from exc

    @classmethod
    def from_bytes(cls, blob: bytes, name: str = "<capture>") -> "CaptureReader":
        self = cls.__new__(cls)
        self.path = name
        self.block_bytes = BLOCK_BYTES
        self._blob = bytes(blob)
        self._parse(self._blob)
        return self

    def _parse(self, blob) -> None:
        self.header, i = _read_header(blob, self.path)
        self.problem = ""
        self.damaged_chunks = self.skipped_bytes = 0
        times, starts, ends = array("d"), array("q"), array("q")
        n, last_t, released = len(blob), -math.inf, 0
        while i < n:
            h = _header_at(blob, i, -math.inf)  # receive times need not rise where nothing is damaged
            if h is None or not _next_ok(blob, h[1], h[0], strict=False):
                found = _resync(blob, i, last_t)
                if found is None:
                    if not _cut_short(blob, i):  # else: a crash mid-write, counted as truncated
                        self._damage(f"damaged chunk structure from byte {i} to the end", n - i)
                        i = n
                    break
                j, t, end = found
                self._damage(f"damaged chunk {'marker' if j == i else 'structure'} at byte {i}", j - i)
                h, i = (t, end), j
            last_t = h[0]
            times.append(last_t)
            starts.append(i + CHUNK_OVERHEAD)
            ends.append(h[1])
            i = h[1]
            if i - released >= self.block_bytes and isinstance(blob, mmap.mmap) and _RELEASE is not None:
                released = i - i % mmap.PAGESIZE  # what lies behind is never looked at again
                blob.madvise(_RELEASE, 0, released)
        self.truncated_bytes = n - i
        if self.truncated_bytes:
            self.problem = self.problem or f"truncated chunk at byte {i} ({self.truncated_bytes} bytes cut)"
        self._starts = np.frombuffer(starts, np.int64)
        self._ends = np.frombuffer(ends, np.int64)
        self.t_rx_s = np.frombuffer(times, np.float64).copy()

    def _damage(self, where: str, skipped: int) -> None:
        self.damaged_chunks += 1
        self.skipped_bytes += skipped
        self.problem = self.problem or where

    def reading(self) -> dict:
        """What reading the file met, by name (for ``Series.reading``)."""
        return {"damaged_chunks": self.damaged_chunks, "skipped_bytes": self.skipped_bytes,
                "truncated_bytes": self.truncated_bytes}

    @property
    def _spans(self) -> list[tuple[int, int]]:
        """(start, end) of each chunk's bytes in the file."""
        return list(zip(self._starts.tolist(), self._ends.tolist()))

    def __len__(self) -> int:
        return len(self._starts)

    def __iter__(self) -> Iterator[tuple[float, bytes]]:
        if self._blob is not None:
            for t, a, b in zip(self.t_rx_s.tolist(), self._starts.tolist(), self._ends.tolist()):
                yield t, self._blob[a:b]
            return
        with open(self.path, "rb") as fh:
            window, w0 = b"", 0  # file bytes from offset w0 on, read ahead in blocks
            for t, a, b in zip(self.t_rx_s.tolist(), self._starts.tolist(), self._ends.tolist()):
                if b > w0 + len(window):
                    fh.seek(a)
                    window, w0 = fh.read(max(self.block_bytes, b - a)), a
                    if len(window) < b - a:
                        raise InputError(f"{self.path}: the file shrank while it was read")
                yield t, window[a - w0 : b - w0]

    def blocks(self) -> Iterator[bytes]:
        """The recorded bytes in order, joined into blocks of about ``block_bytes``."""
        parts, size = [], 0
        for _, chunk in self:
            parts.append(chunk)
            size += len(chunk)
            if size >= self.block_bytes:
                yield b"".join(parts)
                parts, size = [], 0
        if parts:
            yield b"".join(parts)

    def frames(self) -> Frames:
        """All recorded bytes parsed as the live link parses them, read block by block."""
        return parse_blocks(self.blocks())

    def data(self) -> bytes:
        """All recorded bytes, concatenated."""
        return b"".join(chunk for _, chunk in self)


def recorded_dialect(reader: "CaptureReader") -> Dialect:
    """The convention a capture was recorded in. A capture taken with ``--dialect auto`` names
    no convention in its header: its first bytes tell (protocol v1 when they cannot).
    ``InputError`` for a header naming no dialect magcal knows."""
    try:
        dialect = Dialect.named(reader.header.get("dialect") or Dialect.NATIVE)
    except ValueError as exc:
        raise InputError(f"{reader.path} line 1: {exc}") from None
    if dialect is Dialect.AUTO:
        head = b""
        for _, chunk in reader:
            head += chunk
            if len(head) >= 4096:
                break
        dialect = dialect_of(head) or Dialect.NATIVE
    return dialect

