"""Which convention is this serial port speaking? Listen briefly, decide from the first lines."""

from __future__ import annotations

import time

from ..protocol import Framer, Hello, RawSample

LISTEN_S = 1.5
SNIFF_BYTES = 4096


def detect_dialect(port, listen_s: float = LISTEN_S) -> tuple[str, bytes]:
    """Return ("native" | "motioncal", the bytes consumed while listening).

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
    return "native", bytes(seen)


def dialect_of(data: bytes) -> str | None:
    """The convention of the first bytes of a stream or a recording: "native" once a valid v1
    line (hello or sample) is among them, "motioncal" once two or more lines are mostly
    ``Raw:``/``Uni:`` lines, else None (not enough to tell)."""
    from ..motioncal import looks_like_motioncal

    data = bytes(data[:SNIFF_BYTES])
    if any(isinstance(m, (Hello, RawSample)) for m in Framer().feed(data)):
        return "native"
    lines = data.replace(b"\r", b"\n").split(b"\n")[:-1]
    text = [ln.decode("ascii", "replace") for ln in lines if ln.strip()]
    if len(text) >= 2 and looks_like_motioncal(text):
        return "motioncal"
    return None
