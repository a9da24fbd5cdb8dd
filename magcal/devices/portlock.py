"""One process per serial port: a second opener is refused, naming the port and its holder.

A serial device is opened with pyserial's exclusive mode (``exclusive=True``: an advisory
``flock`` on the open device, released by the kernel when the holder exits or is killed). Two
readers of one port would split its byte stream between them, each seeing gaps and torn lines.
When the lock is taken, the holder is looked up in ``/proc/locks`` (Linux: the process holding
a lock on the device's inode) and named with its command line where that can be read.

URLs (``socket://``, ``rfc2217://``, ``loop://``) are not files: the exclusive mode is for
device paths only.
"""

from __future__ import annotations

import errno
import os

from ..core.errors import PortUnavailable

BUSY = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES)


class PortBusy(PortUnavailable):
    """The port is held by another process."""


def is_device_path(url: str) -> bool:
    """A path to a device (``/dev/ttyACM0``, ``COM3``) rather than a pyserial URL."""
    return "://" not in url


def open_exclusive(serial, url: str, baud: int, timeout_s: float):
    """``serial.Serial`` on a device path, exclusively; ``PortBusy`` when another holds it."""
    try:
        return serial.Serial(url, baudrate=baud, timeout=timeout_s, exclusive=True)
    except serial.SerialException as exc:
        if getattr(exc, "errno", None) in BUSY:
            raise PortBusy(f"{url} is in use by {holder_of(url) or 'another process'}; "
                           "one process at a time reads a port") from None
        raise


def holder_of(path: str) -> str | None:
    """Who holds a lock on ``path``: "pid N (command line)", or None when it cannot be told."""
    try:
        st = os.stat(path)
        with open("/proc/locks", encoding="ascii", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    for line in lines:
        pid = _pid_locking(line, st.st_ino)
        if pid is not None and pid != os.getpid():
            return f"pid {pid}{_command(pid)}"
    for line in lines:  # this very process (an earlier open it has not closed)
        pid = _pid_locking(line, st.st_ino)
        if pid is not None:
            return f"pid {pid} (this process)"
    return None


def _pid_locking(line: str, inode: int) -> int | None:
    """The pid of a ``/proc/locks`` line locking ``inode``, else None."""
    parts = line.split()
    if "->" in parts:  # a waiter, not a holder
        return None
    try:
        pid = int(parts[4])
        ino = int(parts[5].rsplit(":", 1)[1])
    except (IndexError, ValueError):
        return None
    return pid if ino == inode else None


def _command(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""
    return f" ({cmd[:200]})" if cmd else ""
