"""The bounds of a setting, declared with the setting: ``setting(default, lo=…, hi=…)`` is a
dataclass field whose metadata says which values are allowed and why; ``bounds_of(field)``
reads them back and ``Bounds.problem(value)`` says what is wrong with a value (pure).

>>> b = Bounds(lo=0, lo_open=True, hi=1)
>>> b.describe()
'in (0, 1]'
>>> b.problem(0.0)
'must be in (0, 1], got 0.0'
>>> b.problem(float("nan"))
'must be a finite number, got nan'
>>> b.problem(0.5) is None
True
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Bounds:
    """Allowed numbers: ``lo``/``hi`` (None: unbounded that side), each end open or closed.
    Every bounded number must be finite. ``why`` is shown after the range."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    why: str = ""

    def describe(self) -> str:
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            return f"in {'(' if self.lo_open else '['}{lo:g}, {hi:g}{')' if self.hi_open else ']'}"
        if lo is not None:
            return f"{'>' if self.lo_open else '≥'} {lo:g}"
        if hi is not None:
            return f"{'<' if self.hi_open else '≤'} {hi:g}"
        return "finite"

    def holds(self, v: float) -> bool:
        try:
            if not math.isfinite(v):
                return False
        except OverflowError:
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return self.hi is None or (v < self.hi if self.hi_open else v <= self.hi)

    def problem(self, v) -> str | None:
        """None when ``v`` is allowed, else what is wrong, as ``must be …, got v``."""
        try:
            finite = math.isfinite(v)
        except OverflowError:  # an integer too large for a float: out of any range
            finite = True
        if not finite:
            return f"must be a finite number, got {_short(v)}"
        if self.holds(v):
            return None
        why = f" ({self.why})" if self.why else ""
        return f"must be {self.describe()}{why}, got {_short(v)}"


def _short(v) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "…"


def setting(default, *, lo=None, hi=None, lo_open=False, hi_open=False, why: str = ""):
    """A dataclass field with ``default`` whose numbers (each element, for a tuple) must lie
    within the given bounds."""
    return dataclasses.field(default=default, metadata={"bounds": Bounds(lo, hi, lo_open, hi_open, why)})


def bounds_of(f: dataclasses.Field) -> Bounds | None:
    return f.metadata.get("bounds") if f.metadata else None


def check_bounds(obj, prefix: str = "") -> None:
    """ConfigError naming the first field of the dataclass ``obj`` whose value (each element,
    for a tuple) is outside its declared bounds; ``keys`` holds its dotted name."""
    from .errors import ConfigError

    for f in dataclasses.fields(obj):
        b = bounds_of(f)
        if b is None:
            continue
        v = getattr(obj, f.name)
        for x in v if isinstance(v, tuple) else (v,):
            problem = b.problem(x)
            if problem:
                raise ConfigError(f"{prefix}{f.name} {problem}", keys=(prefix + f.name,))
