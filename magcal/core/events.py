"""What a device says besides samples: who answered (``Identity``) and what happened on the
link (``Event``). ``Item`` is what a device's ``read`` yields: a sample or an event. ``Code``:
the base of the typed codes decisions are taken on."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Union


class Code(str, Enum):
    """A short code as a typed value: compared, hashed, printed and written to JSON as its
    text (``"timeout"``), so the reports read the same, while code tests it by identity."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

from .chips import Chip, chip_from_ids
from .sample import Sample


@dataclass(frozen=True)
class Identity:
    """Who answered: protocol and firmware versions, chip IDs, the ASA bytes, the rate."""

    transport: str
    proto: int = 1
    firmware: str = ""
    who_am_i: int | None = None
    wia: int | None = None
    asa: tuple[int, int, int] = (128, 128, 128)
    rate_hz: int = 0
    extra: dict = field(default_factory=dict)
    bits: int | None = None  # the magnetometer's output resolution, when the device says it

    @property
    def chip(self) -> Chip | None:
        """The part these ids name (``magcal.core.chips``); None when they name none known."""
        if self.who_am_i is None or self.wia is None:
            return None
        try:
            return chip_from_ids(self.who_am_i, self.wia, self.bits or None)
        except ValueError:
            return None

    def to_dict(self) -> dict:
        d = {
            "transport": self.transport,
            "proto": self.proto,
            "firmware": self.firmware,
            "who_am_i": None if self.who_am_i is None else f"0x{self.who_am_i:02X}",
            "wia": None if self.wia is None else f"0x{self.wia:02X}",
            "asa": list(self.asa),
            "rate_hz": self.rate_hz,
            "chip": None if self.chip is None else self.chip.label,  # always there: one shape per device
        }
        d.update(self.extra)
        return d


@dataclass(frozen=True)
class Event:
    """Something that happened on the link other than a sample.

    kind: ``reset`` (device restarted; ``detail`` says how it was seen), ``gap`` (``count``
    lines lost before ``seq``), ``rejected`` (a sample flagged invalid by the device), ``log``.
    """

    kind: str
    seq: int | None = None
    count: int = 0
    detail: str = ""


Item = Union[Sample, Event]
