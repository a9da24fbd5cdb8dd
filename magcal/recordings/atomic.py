"""Atomic file replacement: a reader sees the old file or the new one, never a torn mix.

``write_atomic(path, data)`` writes ``data`` to a temporary file in the same directory, flushes
it to disk (``fsync``), renames it over ``path`` (atomic on POSIX, and on Windows through
``os.replace``) and then fsyncs the directory so the rename itself survives a power cut.

If the process dies at any point before the rename, ``path`` still holds its old content; a
stray ``.<name>.*.tmp`` file may be left behind, which readers ignore (``TMP_SUFFIX``).

It is the one way magcal writes a file whole (``write_text``, ``save_figure`` for text and
figures): the temporary name is random and created exclusively (``O_EXCL``: never an existing
file, never through a link), and the rename replaces a link planted at ``path`` rather than
writing through it — a planted link never redirects a write to its target.

The new file gets ``mode`` less the process umask, as any file the process creates: under
``umask 077`` (a hardened service) state and calibration files are readable by their owner only.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

TMP_SUFFIX = ".tmp"


def fsync_dir(directory: Path) -> None:
    """Make a rename or a new file in ``directory`` survive a power cut (where the system can)."""
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


def _create_temporary(directory: Path, name: str, mode: int) -> tuple[int, str]:
    """A new file next to the target, created with ``mode`` (the kernel takes the umask off)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        tmp_name = str(directory / f".{name}.{secrets.token_hex(4)}{TMP_SUFFIX}")
        try:
            return os.open(tmp_name, flags, mode), tmp_name
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name for {name} in {directory}")


def write_text(path, text: str, mode: int = 0o644) -> Path:
    """``write_atomic`` of ``text`` in UTF-8."""
    return write_atomic(path, text.encode("utf-8"), mode)


def save_figure(fig, path, check=None, **savefig_options) -> Path:
    """A matplotlib figure as a PNG at ``path``, through ``write_atomic`` (``savefig`` itself
    would open ``path`` and follow a link planted there). ``check``: called with the figure once
    it is rendered (its layout the one saved); what it raises leaves ``path`` untouched."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", **savefig_options)
    if check is not None:
        check(fig)
    return write_atomic(path, buf.getvalue())


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
    fd, tmp_name = _create_temporary(directory, path.name, mode)
    try:
        with os.fdopen(fd, "wb") as fh:
            view = memoryview(data)
            while view:
                n = fh.write(view)
                view = view[n:]
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        raise
    fsync_dir(directory)
    return path
