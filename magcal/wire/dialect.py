"""Which convention a stream of bytes speaks: magcal's protocol v1 or the MotionCal ``Raw:``
convention, decided from its first bytes (a live port's or a recording's)."""

from __future__ import annotations

from .motioncal import looks_like_motioncal
from .protocol import Framer, Hello, RawSample

SNIFF_BYTES = 4096


def dialect_of(data: bytes) -> str | None:
    """The convention of the first bytes of a stream or a recording: "native" once a valid v1
    line (hello or sample) is among them, "motioncal" once two or more lines are mostly
    ``Raw:``/``Uni:`` lines, else None (not enough to tell)."""
    data = bytes(data[:SNIFF_BYTES])
    if any(isinstance(m, (Hello, RawSample)) for m in Framer().feed(data)):
        return "native"
    lines = data.replace(b"\r", b"\n").split(b"\n")[:-1]
    text = [ln.decode("ascii", "replace") for ln in lines if ln.strip()]
    if len(text) >= 2 and looks_like_motioncal(text):
        return "motioncal"
    return None
