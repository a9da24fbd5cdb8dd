"""Atomic file replacement: a reader sees the old file or the new one, never a torn mix.

``write_atomic(path, data)`` writes ``data`` to a temporary file in the same directory, flushes
it to disk (``fsync``), renames it over ``path`` (atomic on POSIX, and on Windows through
``os.replace``) and then fsyncs the directory so the rename itself survives a power cut.

If the process dies at any point before the rename, ``path`` still holds its old content; a
stray ``.<name>.*.tmp`` file may be left behind, which readers ignore (``TMP_SUFFIX``).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

TMP_SUFFIX = ".tmp"


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # e.g. Windows cannot open a directory; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_atomic(path, data: bytes, mode: int = 0o644) -> Path:
    """Replace the file at ``path`` with ``data`` atomically; returns the path.

    Creates the parent directory when needed. Raises ``OSError`` when the directory cannot be
    written; on any failure the temporary file is removed and ``path`` is left untouched.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"write_atomic needs bytes, not {type(data).__name__}")
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=directory)
    try:
        with os.fdopen(fd, "wb") as fh:
            view = memoryview(data)
            while view:
                n = fh.write(view)
                view = view[n:]
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp_name, mode)
        os.replace(tmp_name, path)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(directory)
    return path
