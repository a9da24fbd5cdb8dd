"""Which convention a stream of bytes speaks: magcal's protocol v1 or the MotionCal ``Raw:``
convention, decided from its first bytes (a live port's or a recording's)."""

from __future__ import annotations

import enum

from .motioncal import looks_like_motioncal
from .protocol import Framer, Hello, RawSample

SNIFF_BYTES = 4096


class Dialect(enum.Enum):
    """The convention a link or a capture speaks; ``AUTO``: decided from its first bytes.
    Text (a setting, an option, a capture header) becomes one at the edge (``Dialect.named``)."""

    NATIVE = "native"
    MOTIONCAL = "motioncal"
    AUTO = "auto"

    @classmethod
    def named(cls, name: "str | Dialect") -> "Dialect":
        """The dialect ``name`` spells; ``ValueError`` naming the choices for anything else."""
        if isinstance(name, cls):
            return name
        for d in cls:
            if name == d.value:
                return d
        raise ValueError(f"unknown dialect {name!r} ({', '.join(d.value for d in cls)})")


def dialect_of(data: bytes) -> Dialect | None:
    """The convention of the first bytes of a stream or a recording: native once a valid v1
    line (hello or sample) is among them, MotionCal once two or more lines are mostly
    ``Raw:``/``Uni:`` lines, else None (not enough to tell)."""
    data = bytes(data[:SNIFF_BYTES])
    if any(isinstance(m, (Hello, RawSample)) for m in Framer().feed(data)):
        return Dialect.NATIVE
    lines = data.replace(b"\r", b"\n").split(b"\n")[:-1]
    text = [ln.decode("ascii", "replace") for ln in lines if ln.strip()]
    if len(text) >= 2 and looks_like_motioncal(text):
        return Dialect.MOTIONCAL
    return None
