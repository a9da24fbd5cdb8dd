"""A fleet's compasses across flights: each (vehicle, compass)'s calibration in flight order,
and the flights where it changed, each change judged against the uncertainties of the flights
on both sides of it.

A history is the flights' fitted hard iron ``offset_ut`` (and the current term ``k`` µT/A where
the flight-log fit judged one) with their reported 1σ. A change is found by scanning every split
of the history into an earlier and a later run of flights: the σ-weighted means of the two runs
differ by Δ with variance Σ_axis (1/W_before + 1/W_after), χ² = Σ Δ²/var (3 degrees of freedom),
and the split with the largest χ² is the candidate. Its p-value is Bonferroni-corrected for the
n − 1 splits looked at, and a vehicle's tests share the family-wise level ``alpha`` (each test
gets alpha / the vehicle's number of tests), so an unchanged vehicle is called changed at most
``alpha`` of the time. Flights that scatter more than their σ say (χ²/dof of the runs about
their means above 1) widen every σ by that ratio first (Birge), so an optimistic σ does not
become a change. A found change splits the history and each side is searched again (several
changes on one compass). The flight named is the first flight of the later run.

What changed: the hard iron (a magnetised part, a moved battery or cable: ``HARD_IRON_STEP``) or
the current term (``CURRENT_TERM_APPEARED`` when the earlier run is consistent with none,
``CURRENT_TERM_CHANGED`` otherwise: an ageing ESC, a re-routed motor cable). Each change also
says whether the vehicle's other compasses moved at the same flight (the same split, tested
without the scan): a change on one compass alone means it no longer agrees with its siblings
(something near that compass), on all of them something on the vehicle.

Pure: rows in (dicts with the keys of ``Flight.from_row``), values out.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from ..fit.tails import chi2_sf

ALPHA = 0.01  # family-wise false-change level per vehicle


class ChangeKind(Enum):
    HARD_IRON_STEP = "hard_iron_step"
    CURRENT_TERM_APPEARED = "current_term_appeared"
    CURRENT_TERM_CHANGED = "current_term_changed"


class Quantity(Enum):
    OFFSET = "offset_ut"
    CURRENT = "current_a_ut_per_unit"


@dataclass(frozen=True)
class Flight:
    """One flight of one compass as the history needs it (None: not fitted on that flight)."""

    file: str
    time: float | None  # decimal year; None when the log has no date (ordered by file then)
    offset_ut: np.ndarray | None
    sigma_offset_ut: np.ndarray | None
    current_ut_per_a: np.ndarray | None
    sigma_current_ut_per_a: np.ndarray | None

    @classmethod
    def from_row(cls, row: dict) -> "Flight":
        def vec(key):
            v = row.get(key)
            return None if v is None or len(v) != 3 or not np.all(np.isfinite(v)) else np.asarray(v, np.float64)

        t = row.get("flight_year")
        return cls(file=row["path"], time=None if t is None or not np.isfinite(t) else float(t),
                   offset_ut=vec("offset_ut"), sigma_offset_ut=vec("sigma_offset_ut"),
                   current_ut_per_a=vec("current_a_ut_per_unit"),
                   sigma_current_ut_per_a=vec("sigma_current_a_ut_per_unit"))

    def value(self, q: Quantity) -> tuple[np.ndarray, np.ndarray] | None:
        x, s = ((self.offset_ut, self.sigma_offset_ut) if q is Quantity.OFFSET
                else (self.current_ut_per_a, self.sigma_current_ut_per_a))
        return None if x is None or s is None or not np.all(s > 0) else (x, s)


@dataclass(frozen=True)
class Split:
    """Flights [0, k) against [k, n) of one quantity: the two runs' weighted means and the test."""

    k: int
    before: np.ndarray
    after: np.ndarray
    sigma_step: np.ndarray
    sigma_before: np.ndarray  # of the earlier run's mean
    chi2: float
    widened: float  # the factor every σ was widened by (≥ 1)

    @property
    def step(self) -> np.ndarray:
        return self.after - self.before


@dataclass(frozen=True)
class SiblingCheck:
    compass: str
    moved: bool
    step: tuple[float, float, float]
    chi2: float
    p_value: float


@dataclass(frozen=True)
class Change:
    vehicle: str
    compass: str
    kind: ChangeKind
    flight: str  # the first flight after the change
    previous_flight: str  # the last flight before it
    index: int  # of ``flight`` in the compass's history
    before: tuple[float, float, float]
    after: tuple[float, float, float]
    sigma_step: tuple[float, float, float]
    chi2: float
    p_value: float  # corrected for the splits looked at
    widened: float
    adjacent_chi2: float  # the two flights either side alone, through their own σ
    siblings: tuple[SiblingCheck, ...] = ()

    @property
    def alone(self) -> bool | None:
        """True: no sibling moved at this flight (this compass no longer agrees with them)."""
        return None if not self.siblings else not any(s.moved for s in self.siblings)

    def to_dict(self) -> dict:
        step = np.subtract(self.after, self.before)
        return {"vehicle": self.vehicle, "compass": self.compass, "kind": self.kind.value, "flight": self.flight,
                "previous_flight": self.previous_flight, "index": self.index, "before": list(self.before),
                "after": list(self.after), "step": [float(v) for v in step], "step_norm": float(np.linalg.norm(step)),
                "sigma_step": list(self.sigma_step), "chi2": self.chi2, "p_value": self.p_value,
                "sigma_widened_by": self.widened, "adjacent_chi2": self.adjacent_chi2, "alone": self.alone,
                "siblings": [{"compass": s.compass, "moved": s.moved, "step": list(s.step), "chi2": s.chi2,
                              "p_value": s.p_value} for s in self.siblings]}


def split_at(x: np.ndarray, s: np.ndarray, k: int, widen: bool = True) -> Split:
    """The test of flights [0, k) against [k, n): σ widened by the runs' own scatter when it
    exceeds what their σ say."""
    w = 1.0 / s ** 2
    ml = np.sum(w[:k] * x[:k], 0) / np.sum(w[:k], 0)
    mr = np.sum(w[k:] * x[k:], 0) / np.sum(w[k:], 0)
    factor = 1.0
    dof = 3 * (len(x) - 2)
    if widen and dof > 0:
        scatter = np.sum(w[:k] * (x[:k] - ml) ** 2) + np.sum(w[k:] * (x[k:] - mr) ** 2)
        factor = max(1.0, float(scatter / dof))
    var = factor * (1.0 / np.sum(w[:k], 0) + 1.0 / np.sum(w[k:], 0))
    chi2 = float(np.sum((mr - ml) ** 2 / var))
    return Split(k=k, before=ml, after=mr, sigma_step=np.sqrt(var), sigma_before=np.sqrt(factor / np.sum(w[:k], 0)),
                 chi2=chi2, widened=float(np.sqrt(factor)))


def best_split(x: np.ndarray, s: np.ndarray) -> tuple[Split, float] | None:
    """The split with the largest χ² (scanned without widening, then judged with it) and its
    p-value corrected for the n − 1 splits; None for fewer than two flights."""
    n = len(x)
    if n < 2:
        return None
    w = 1.0 / s ** 2
    cw, cwx = np.cumsum(w, 0), np.cumsum(w * x, 0)
    wl, wr = cw[:-1], cw[-1] - cw[:-1]
    ml, mr = cwx[:-1] / wl, (cwx[-1] - cwx[:-1]) / wr
    chi2 = np.sum((mr - ml) ** 2 / (1.0 / wl + 1.0 / wr), axis=1)
    sp = split_at(x, s, int(np.argmax(chi2)) + 1)
    return sp, min(1.0, (n - 1) * float(chi2_sf(sp.chi2, 3)))


def _segments(x, s, alpha_each: float, lo: int = 0, depth: int = 0):
    """(index of the first flight after, split, p) of every change: binary segmentation."""
    got = best_split(x[lo:], s[lo:]) if len(x) - lo >= 2 else None
    if got is None or got[1] >= alpha_each or depth > 8:
        return []
    sp, p = got
    k = lo + sp.k
    left = _segments(x[:k], s[:k], alpha_each, lo, depth + 1)
    right = _segments(x, s, alpha_each, k, depth + 1)
    return left + [(k, sp, p)] + right


def _kind(q: Quantity, sp: Split) -> ChangeKind:
    if q is Quantity.OFFSET:
        return ChangeKind.HARD_IRON_STEP
    zero = float(chi2_sf(float(np.sum((sp.before / sp.sigma_before) ** 2)), 3)) > ALPHA
    return ChangeKind.CURRENT_TERM_APPEARED if zero else ChangeKind.CURRENT_TERM_CHANGED


@dataclass(frozen=True)
class CompassHistory:
    """One compass of one vehicle, its flights in order."""

    vehicle: str
    compass: str
    flights: tuple[Flight, ...]
    rows: tuple[dict, ...] = field(default=(), compare=False)

    def series(self, q: Quantity) -> tuple[list[int], np.ndarray, np.ndarray]:
        """(indices of the flights where ``q`` was fitted, values (m, 3), σ (m, 3))."""
        got = [(i, f.value(q)) for i, f in enumerate(self.flights)]
        got = [(i, v) for i, v in got if v is not None]
        if not got:
            return [], np.zeros((0, 3)), np.zeros((0, 3))
        return [i for i, _ in got], np.array([v[0] for _, v in got]), np.array([v[1] for _, v in got])


def _order_key(f: Flight):
    return (f.time is None, f.time if f.time is not None else 0.0, f.file)


def histories(rows: list[dict]) -> list[CompassHistory]:
    """Every (vehicle, compass) with its flights in time order (then file name). Rows without
    a compass (a file that could not be read) belong to no history."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if r.get("compass"):
            groups.setdefault((r["vehicle"], r["compass"]), []).append(r)
    out = []
    for (vehicle, compass), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: _order_key(Flight.from_row(r)))
        out.append(CompassHistory(vehicle, compass, tuple(Flight.from_row(r) for r in rs), tuple(rs)))
    return out


def _changes_of(h: CompassHistory, q: Quantity, alpha_each: float) -> list[Change]:
    idx, x, s = h.series(q)
    out = []
    for k, sp, p in _segments(x, s, alpha_each):
        i, j = idx[k - 1], idx[k]
        adj = float(np.sum((x[k] - x[k - 1]) ** 2 / (s[k] ** 2 + s[k - 1] ** 2)))
        out.append(Change(vehicle=h.vehicle, compass=h.compass, kind=_kind(q, sp), flight=h.flights[j].file,
                          previous_flight=h.flights[i].file, index=j, before=_t(sp.before), after=_t(sp.after),
                          sigma_step=_t(sp.sigma_step), chi2=sp.chi2, p_value=p, widened=sp.widened,
                          adjacent_chi2=adj))
    return out


def _t(v) -> tuple[float, float, float]:
    return tuple(float(a) for a in v)


def _sibling_check(change: Change, q: Quantity, sib: CompassHistory, alpha: float) -> SiblingCheck | None:
    """The sibling's same quantity split at the same flight (the same log file; no scan: the
    flight is given); None where the sibling has no such flight or nothing before it."""
    idx, x, s = sib.series(q)
    files = [sib.flights[i].file for i in idx]
    k = files.index(change.flight) if change.flight in files else 0
    if k == 0:
        return None
    sp = split_at(x, s, k)
    p = float(chi2_sf(sp.chi2, 3))
    return SiblingCheck(compass=sib.compass, moved=p < alpha, step=_t(sp.step), chi2=sp.chi2, p_value=p)


@dataclass(frozen=True)
class FleetReport:
    histories: tuple[CompassHistory, ...]
    changes: tuple[Change, ...]
    alpha: float

    def vehicles(self) -> list[str]:
        return sorted({h.vehicle for h in self.histories})

    def changes_of(self, vehicle: str, compass: str | None = None) -> list[Change]:
        return [c for c in self.changes if c.vehicle == vehicle and (compass is None or c.compass == compass)]


def detect(rows: list[dict], alpha: float = ALPHA) -> FleetReport:
    """Every history of ``rows`` and every change found in it (see the module's docstring)."""
    hs = histories(rows)
    by_vehicle: dict[str, list[CompassHistory]] = {}
    for h in hs:
        by_vehicle.setdefault(h.vehicle, []).append(h)
    changes = []
    for vehicle, group in by_vehicle.items():
        tests = [(h, q) for h in group for q in Quantity if len(h.series(q)[0]) >= 2]
        alpha_each = alpha / max(1, len(tests))
        for h, q in tests:
            for c in _changes_of(h, q, alpha_each):
                sibs = [_sibling_check(c, q, o, alpha) for o in group if o is not h]
                changes.append(_with_siblings(c, tuple(s for s in sibs if s is not None)))
    changes.sort(key=lambda c: (c.vehicle, c.compass, c.index, c.kind.value))
    return FleetReport(histories=tuple(hs), changes=tuple(changes), alpha=alpha)


def _with_siblings(c: Change, sibs: tuple[SiblingCheck, ...]) -> Change:
    return replace(c, siblings=sibs)
