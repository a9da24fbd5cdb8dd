"""The gates a calibration must pass before it is written: the thresholds (``Gates``, a value
read from the configuration), the verdict on each (``GateResult``), and the one decision every
writing path takes (``clear_for_write`` → ``Clearance``).

``calibrate``, ``run`` and ``write`` all write through ``app.procedure.write_verified``, which
takes a ``Clearance`` and refuses one that does not allow the write — so a gate means the same
everywhere and none can be skipped. ``force=True`` (``magcal write --force``) lets a write past
failing gates; the clearance then says so, and so does every report of that write.

A gate whose evidence is missing (a calibration object alone says nothing about its residuals)
is *not judged*: ``passed`` is None and the message says what was missing. Only judged gates
can refuse a write; the unjudged ones are named in the report.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.bounds import check_bounds, setting
from ..core.calibration import EARTH_FIELD_UT
from ..core.errors import ConfigError
from ..fit.coverage import DEFAULT_BANDS, DEFAULT_SECTORS

KEPT_MAX = 8 * DEFAULT_BANDS * DEFAULT_SECTORS  # the session keeps at most this many samples


@dataclass(frozen=True)
class Gates:
    """What a calibration must show before it is written."""

    # samples kept for the fit (direction-balanced)
    min_samples: int = setting(300, lo=10, hi=KEPT_MAX, why=f"the fit keeps at most {KEPT_MAX} samples")
    # share of the 128 equal-area direction cells visited
    min_coverage: float = setting(0.55, lo=0, lo_open=True, hi=1)
    # RMS of |calibrated| − field over the kept samples
    max_rms_ut: float = setting(2.0, lo=0, lo_open=True)
    # accepted field radius (Earth: 22–67 µT)
    field_range_ut: tuple[float, float] = setting(EARTH_FIELD_UT, lo=0, lo_open=True, hi=1e4)
    # |offset| beyond this is a magnet, not hard iron
    max_offset_ut: float = setting(1000.0, lo=0, lo_open=True)
    # 1σ uncertainty of each offset axis
    max_offset_sigma_ut: float = setting(0.5, lo=0, lo_open=True)
    # of the normal matrix: thin coverage ⇒ large
    max_condition: float = setting(300.0, lo=1)

    def check(self) -> None:
        """ConfigError naming the first setting out of bounds (also for Gates built in code)."""
        check_bounds(self, "gates.")
        lo_hi = self.field_range_ut
        if len(lo_hi) != 2 or not lo_hi[0] < lo_hi[1]:
            raise ConfigError(f"gates.field_range_ut must be two increasing positive numbers [low, high], "
                              f"got {list(lo_hi)}", keys=("gates.field_range_ut",))


@dataclass(frozen=True)
class GateResult:
    name: str
    passed: bool | None  # None: not judged (its evidence is missing)
    value: float | None
    limit: object
    message: str

    def to_dict(self) -> dict:
        """JSON-ready: a value too large to be a number in JSON (an offset of 1e308 on three
        axes) is given as a string."""
        value = self.value
        if value is not None and not np.isfinite(value):
            value = str(value)
        return {"gate": self.name, "passed": self.passed, "value": value, "limit": self.limit, "message": self.message}


@dataclass(frozen=True)
class Evidence:
    """What is known of a calibration about to be written. The first two are always known;
    the rest come from the fit (or the file) and may be missing."""

    offset_ut: tuple
    field_ut: float
    rms_ut: float | None = None
    offset_sigma_ut: tuple | None = None  # 1σ per axis
    n_used: int | None = None  # samples the fit used
    coverage: float | None = None
    condition: float | None = None


@dataclass(frozen=True)
class Clearance:
    """The decision on one calibration: each gate's verdict, and whether the write was forced."""

    evidence: Evidence
    results: tuple
    forced: bool = False

    @property
    def failing(self) -> list[GateResult]:
        return [r for r in self.results if r.passed is False]

    @property
    def unjudged(self) -> list[GateResult]:
        return [r for r in self.results if r.passed is None]

    @property
    def blocking(self) -> list[GateResult]:
        """What stands in the way of a write: every failing gate, then every gate that could
        not be judged (a gate without its evidence is never taken as passed)."""
        return self.failing + self.unjudged

    @property
    def allowed(self) -> bool:
        return self.forced or not self.blocking

    def covers(self, offset_ut, field_ut: float) -> bool:
        """Is this the clearance of that calibration (to 1 nT, the record's resolution)?"""
        off = np.asarray(self.evidence.offset_ut, np.float64) - np.asarray(offset_ut, np.float64)
        return bool(np.all(np.abs(off) <= 1e-3) and abs(self.evidence.field_ut - float(field_ut)) <= 1e-3)

    def summary(self) -> str:
        if not self.failing:
            text = "every judged gate passed" if not self.unjudged or self.forced else "NOT every gate judged"
        else:
            text = ("FORCED past failing gates: " if self.forced else "failing gates: ") + "; ".join(
                r.message for r in self.failing)
        if self.unjudged:
            text += " (not judged: " + ", ".join(r.name for r in self.unjudged) + ")"
        return text

    def to_dict(self) -> dict:
        return {"allowed": self.allowed, "forced": self.forced,
                "failing": [r.name for r in self.failing], "not_judged": [r.name for r in self.unjudged],
                "results": [r.to_dict() for r in self.results]}


def _unjudged(name: str, limit, missing: str) -> GateResult:
    return GateResult(name, None, None, limit, f"{name}: not judged ({missing} not known)")


def model_gates(g: Gates, offset_ut, field_ut, rms_ut, sigma_ut) -> list[GateResult]:
    """The gates on a fitted model: field radius, offset size, residual RMS and offset
    uncertainty (1σ per axis); RMS and σ not judged when None."""
    lo, hi = g.field_range_ut
    off = float(np.linalg.norm(offset_ut))
    field_ut = float(field_ut)
    out = [
        GateResult("field_range", bool(lo <= field_ut <= hi), field_ut, [lo, hi],
                   f"field radius {field_ut:.1f} µT (accepted {lo:g}–{hi:g})"),
        GateResult("max_offset", bool(off <= g.max_offset_ut), off, g.max_offset_ut,
                   f"|offset| {off:.1f} µT (≤ {g.max_offset_ut:g})"),
    ]
    if rms_ut is None:
        out.append(_unjudged("max_rms", g.max_rms_ut, "the residual RMS"))
    else:
        out.append(GateResult("max_rms", bool(rms_ut <= g.max_rms_ut), float(rms_ut), g.max_rms_ut,
                              f"residual RMS {rms_ut:.2f} µT (≤ {g.max_rms_ut:g})"))
    if sigma_ut is None:
        out.append(_unjudged("max_offset_sigma", g.max_offset_sigma_ut, "the offset uncertainty"))
    else:
        sig = float(np.max(sigma_ut))
        out.append(GateResult("max_offset_sigma", bool(sig <= g.max_offset_sigma_ut), sig, g.max_offset_sigma_ut,
                              f"offset uncertainty {sig:.3f} µT 1σ (≤ {g.max_offset_sigma_ut:g})"))
    return out


def data_gates(g: Gates, samples, coverage, condition) -> list[GateResult]:
    """The gates on the data behind a fit: samples kept, direction coverage, conditioning."""
    out = []
    if samples is None:
        out.append(_unjudged("min_samples", g.min_samples, "the number of samples"))
    else:
        out.append(GateResult("min_samples", samples >= g.min_samples, float(samples), g.min_samples,
                              f"{samples} of {g.min_samples} well-spread samples"))
    if coverage is None:
        out.append(_unjudged("min_coverage", g.min_coverage, "the direction coverage"))
    else:
        out.append(GateResult("min_coverage", coverage >= g.min_coverage, float(coverage), g.min_coverage,
                              f"{100 * coverage:.0f}% of directions covered, {100 * g.min_coverage:.0f}% needed"))
    if condition is None:
        out.append(_unjudged("max_condition", g.max_condition, "the conditioning"))
    else:
        out.append(GateResult("max_condition", bool(condition <= g.max_condition), float(condition),
                              g.max_condition, f"normal-matrix condition {condition:.0f} (≤ {g.max_condition:.0f})"))
    return out


def clear_for_write(g: Gates, ev: Evidence, force: bool = False) -> Clearance:
    """THE decision before a calibration is written, for every path that writes. A field or
    offset that is not a finite number fails its gate (it can never be forced past)."""
    finite = bool(np.all(np.isfinite(np.asarray(ev.offset_ut, np.float64))) and np.isfinite(ev.field_ut))
    results = data_gates(g, ev.n_used, ev.coverage, ev.condition)
    results += model_gates(g, ev.offset_ut, ev.field_ut, ev.rms_ut, ev.offset_sigma_ut)
    if not finite:
        results.append(GateResult("finite", False, None, None, "the calibration holds a number that is not finite"))
    return Clearance(ev, tuple(results), forced=bool(force and finite))
