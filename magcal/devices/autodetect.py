"""Which convention is this serial port speaking? Listen briefly, decide from the first lines."""

from __future__ import annotations

import time

from ..wire.dialect import SNIFF_BYTES, Dialect, dialect_of

LISTEN_S = 1.5


def detect_dialect(port, listen_s: float = LISTEN_S) -> tuple[Dialect, bytes]:
    """Return (native or MotionCal, the bytes consumed while listening).

    Valid v1 lines (correct CRC-8) mean native; ``Raw:``/``Uni:`` lines mean MotionCal. With
    nothing recognisable, native is assumed (the v1 client then asks the device to identify).
    """
    seen = bytearray()
    deadline = time.monotonic() + listen_s
    while time.monotonic() < deadline and len(seen) < SNIFF_BYTES:
        port.timeout = 0.05
        chunk = port.read(max(1, port.in_waiting or 1))
        if not chunk:
            continue
        seen += chunk
        found = dialect_of(bytes(seen))
        if found:
            return found, bytes(seen)
    return Dialect.NATIVE, bytes(seen)
