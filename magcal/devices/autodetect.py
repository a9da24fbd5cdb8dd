"""Which convention is this serial port speaking? Listen briefly, decide from the first lines."""

from __future__ import annotations

import time

from ..protocol import Framer, Hello, RawSample

LISTEN_S = 1.5


def detect_dialect(port, listen_s: float = LISTEN_S) -> tuple[str, bytes]:
    """Return ("native" | "motioncal", the bytes consumed while listening).

    Valid v1 lines (correct CRC-8) mean native; ``Raw:``/``Uni:`` lines mean MotionCal. With
    nothing recognisable, native is assumed (the v1 client then asks the device to identify).
    """
    from ..motioncal import looks_like_motioncal

    seen = bytearray()
    deadline = time.monotonic() + listen_s
    while time.monotonic() < deadline and len(seen) < 4096:
        port.timeout = 0.05
        chunk = port.read(max(1, port.in_waiting or 1))
        if not chunk:
            continue
        seen += chunk
        lines = bytes(seen).replace(b"\r", b"\n").split(b"\n")[:-1]
        if any(isinstance(m, (Hello, RawSample)) for m in Framer().feed(bytes(seen))):
            return "native", bytes(seen)
        text = [ln.decode("ascii", "replace") for ln in lines if ln.strip()]
        if len(text) >= 2 and looks_like_motioncal(text):
            return "motioncal", bytes(seen)
    return "native", bytes(seen)
