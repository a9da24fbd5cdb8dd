"""How a diagnosis says a time, a stretch, a duration or a frequency in words.

A recording without a clock (``Series.clock`` false: a table of x, y, z alone) is timed by its
sample index, so every ``time_s`` its diagnosis holds counts samples and every ``frequency_hz``
cycles per sample. The JSON keeps those numbers under the same keys (the result's ``clock:
false`` says how to read them); the words must not call them seconds. "At 10493.0 s" on a file
of 12 000 rows with no time column is a unit the recording never had.

The unit is the diagnosed recording's, one for the whole diagnosis: ``in_recording_time`` sets
it for the call of a function whose argument ``series`` is the recording (``diagnose``, the twin's
comparison), and every statement built during that call reads it here. A context variable, not
an argument threaded through every search: only the words depend on it, each concurrent
diagnosis (a thread, a worker) keeps its own, and outside a call the unit is seconds.
"""

from __future__ import annotations

import functools
import inspect
from contextvars import ContextVar

_CLOCKED: ContextVar[bool] = ContextVar("magcal_diagnosis_clocked", default=True)


def clocked() -> bool:
    """Whether the recording being diagnosed has a clock (its t_s are seconds)."""
    return _CLOCKED.get()


def in_recording_time(fn):
    """Run ``fn`` with its statements said in the time of its argument ``series``: seconds and
    hertz where that recording has a clock, samples and cycles per sample where it has none."""
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def said_in_its_time(*args, **kwargs):
        series = signature.bind(*args, **kwargs).arguments["series"]
        token = _CLOCKED.set(bool(series.clock))
        try:
            return fn(*args, **kwargs)
        finally:
            _CLOCKED.reset(token)

    return said_in_its_time


def instant(t: float, spec: str = ".1f") -> str:
    """'40.0 s', or 'sample 10493' without a clock."""
    return f"{t:{spec}} s" if clocked() else f"sample {t:.0f}"


def stretch(a: float, b: float, spec: str = ".1f") -> str:
    """'10.0–20.0 s', or 'samples 100–200' without a clock."""
    return f"{a:{spec}}–{b:{spec}} s" if clocked() else f"samples {a:.0f}–{b:.0f}"


def duration(d: float, spec: str = ".1f") -> str:
    """'2.5 s', or '250 samples' without a clock."""
    sign = "+" if spec.startswith("+") else ""
    return f"{d:{spec}} s" if clocked() else f"{d:{sign}.0f} samples"


def frequency(f: float, spec: str = ".3f") -> str:
    """'29.118 Hz', or '0.0123 cycles per sample' without a clock."""
    return f"{f:{spec}} Hz" if clocked() else f"{f:.4f} cycles per sample"


def frequencies(fs, spec: str = ".3f") -> str:
    """'0.111, 0.222 Hz', or in cycles per sample without a clock."""
    if clocked():
        return ", ".join(f"{f:{spec}}" for f in fs) + " Hz"
    return ", ".join(f"{f:.4f}" for f in fs) + " cycles per sample"


def duration_range(lo: float, hi: float, spec: str = ".1f") -> str:
    """'0.2–0.4 s' (a lag's interval, say), or '2–4 samples' without a clock."""
    return f"{lo:{spec}}–{hi:{spec}} s" if clocked() else f"{lo:.0f}–{hi:.0f} samples"
