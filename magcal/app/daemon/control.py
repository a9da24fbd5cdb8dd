"""The control socket: a local UNIX socket ``status.sock`` in the state directory that answers
each connection with the daemon's status as one JSON object (``magcal status``). There is no
network listener; the socket never blocks the loop."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path
from typing import Callable

import numpy as np

from .journal import Decision, Journal

SOCKET_NAME = "status.sock"


class ControlSocket:
    def __init__(self, state_dir: Path, journal: Journal):
        self.path = Path(state_dir) / SOCKET_NAME
        self._journal = journal
        self._sock: socket.socket | None = None

    def open(self) -> None:
        if not hasattr(socket, "AF_UNIX"):
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.exists() or self.path.is_symlink():
                self.path.unlink()
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.bind(str(self.path))
            os.chmod(self.path, 0o660)
            sock.listen(4)
            sock.setblocking(False)
        except OSError as exc:
            self._journal.record(Decision.SOCKET_UNAVAILABLE, error=str(exc))
            return
        self._sock = sock

    def serve(self, status: Callable[[], dict]) -> None:
        """Answer every waiting connection with ``status()``."""
        if self._sock is None:
            return
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:  # BlockingIOError: nobody waiting
                return
            try:
                conn.settimeout(1.0)
                conn.sendall(json.dumps(status(), allow_nan=False, default=_json_default).encode() + b"\n")
            except (OSError, ValueError):
                pass
            finally:
                conn.close()

    def close(self) -> None:
        if self._sock is None:
            return
        self._sock.close()
        self._sock = None
        try:
            self.path.unlink()
        except OSError:
            pass


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def query_socket(state_dir, timeout_s: float = 2.0) -> dict | None:
    """The live status from a running daemon's socket; None when nobody answers."""
    path = Path(state_dir).expanduser() / SOCKET_NAME
    if not hasattr(socket, "AF_UNIX") or not path.exists():
        return None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
        chunks = []
        while True:
            b = s.recv(65536)
            if not b:
                break
            chunks.append(b)
    except OSError:
        return None
    finally:
        s.close()
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        return None
