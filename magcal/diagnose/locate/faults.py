"""Data faults, screened on the raw series before any fit: stuck axes, clipped rails, swapped
or sign-flipped axes, and timestamps that repeat or run backwards.

``screen(t_s, m_ut, valid=None) -> Screen`` returns ``keep`` (the samples to use) and ``found``
(one ``Located`` of kind ``Kind.FAULT`` per fault, with the rows it sets aside, the stretches in
time and the axis). Every threshold is judged against the recording itself:

- ``repeated_timestamps`` / ``out_of_order_timestamps``: a sample whose time is not later than
  every time before it. Set aside (its time says nothing about where it belongs).
- ``saturation``: a pile-up at an axis's extreme value — the same raw value at the max (or
  min) in at least ``RAIL_MIN_SHARE`` of the distinct readings and ``RAIL_OVER_LEVEL`` times the
  typical (median) count of the ``RAIL_LEVELS`` distinct readings just inside it. Quantised real data visit their extreme level a few
  times (the field only brushes it); a rail collects every sample the sensor could not reach,
  so its samples lie inside the surface fitted without them (an axis stuck at its extreme
  reads more than the field, lies outside, and is left to the stuck-axis search).
- ``stuck_axis``: one axis repeating its exact value for a run while the other two move (by
  ``MOVE_QUANTA`` of their own quantisation step and beyond what the residual scatter spans)
  and the surface fitted on the rest of the data says that axis should have changed: the
  run's radial residual is ``STUCK_OVER_FLOOR`` times the recording's robust scatter and
  ``STUCK_OVER_LOCAL`` times that of the samples around it. A slow board turning about that
  axis, or one held nearly still, repeats an axis legitimately and stays on the surface.
  A run is counted in readings, ``STUCK_MIN_SAMPLES`` at least: a row repeating every axis of
  the row before (a logger faster than its sensor writing one reading twice) is no axis
  holding while the others move, and adds no reading to the run.
- ``axis_swap``: a stretch the surface fitted on the rest of the data misses as read
  (``SWAP_MISS`` × scatter) but fits (within ``SWAP_FIT`` × scatter) with two axes exchanged
  or one axis negated, for at least ``SWAP_MIN_SAMPLES`` samples with no sample in between
  that fits as read. A stretch shorter than that (a slow log: a few readings) or one the radius
  cannot see (the offsets of the exchanged axes equal, so the swap maps the surface onto itself)
  is found by its total evidence (``swap_evidence``): the radial residual's log-likelihood gain
  transformed over as read, judged against the recording's own scatter and the number of
  stretches tried and passing the same contrast; or the jumps at both its ends, each beyond the
  recording's typical step there and an ordinary step read back through the transform. Where
  the offset is near zero and the board barely moves a swap is invisible, and harmless to the
  calibration.

The surface is ``magcal.fit.fit_calibration`` (robust start, Grubbs, ML; an ellipsoid where the
coverage determines one), taken as the one with the least median radial residual over all
samples among the fits on all samples and on all but two adjacent blocks of ``FIT_BLOCKS``, so that a faulty stretch up to two fifths long cannot bend it; once faults are
found the fits are redone without them and the search repeated once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.calibration import Calibration
from ...fit import fit_calibration
from .. import timewords
from . import swap_evidence
from .base import AXES, Effect, Kind, Located, Residual, repeats, runs

RAIL_MIN_SHARE = 0.005  # share of distinct readings a rail must hold
RAIL_MIN_COUNT = 8
RAIL_OVER_LEVEL = 3.0  # the rail against the typical (median) level just inside it
RAIL_LEVELS = 5  # "just inside": this many distinct readings nearest the extreme
STUCK_MIN_SAMPLES = 4  # readings (rows logged twice not counted); 3 takes three-reading glitches of a real RM3100 log (estibone)
MOVE_QUANTA = 10.0
STUCK_OVER_FLOOR = 4.0
STUCK_OVER_LOCAL = 3.0
SWAP_MISS = 10.0  # a sample missed by this × scatter as read ...
SWAP_FIT = 3.0  # ... and fitted within this × scatter transformed favours the transform
SWAP_RATIO = 5.0  # the stretch: RMS as read against RMS transformed
SWAP_OVER_LOCAL = 3.0  # the stretch as read against the samples around it
SWAP_MIN_SAMPLES = 10
FIT_MAX_N = 1000
FIT_BLOCKS = 5
FIT_MODEL = "ellipsoid"
MAD_TO_SIGMA = 1.4826

# the readings a stretch may have been taken in: (name, permutation, signs); each is its own inverse
TRANSFORMS = (
    ("x↔y", (1, 0, 2), (1, 1, 1)),
    ("x↔z", (2, 1, 0), (1, 1, 1)),
    ("y↔z", (0, 2, 1), (1, 1, 1)),
    ("−x", (0, 1, 2), (-1, 1, 1)),
    ("−y", (0, 1, 2), (1, -1, 1)),
    ("−z", (0, 1, 2), (1, 1, -1)),
)


@dataclass(frozen=True)
class Screen:
    """What the screen decided: ``keep`` (n,) the samples to use; ``found`` the faults."""

    keep: np.ndarray
    found: tuple[Located, ...]

    @property
    def n_set_aside(self) -> int:
        return int(len(self.keep) - np.count_nonzero(self.keep))


def screen(t_s, m_ut, valid=None) -> Screen:
    """Screen the raw series (rows in acquisition order) for data faults; see the module docstring."""
    t, m, keep = _inputs(t_s, m_ut, valid)
    found = list(_timestamps(t, keep))
    keep = _without(keep, found)
    found += _outward_rails_dropped(m, keep, _saturation(t, m, keep))
    keep = _without(keep, found)
    shape, fit_on = [], keep
    for _ in range(2):  # the second pass fits without what the first found
        held = _held_out(m, keep, fit_on, fit_on is keep)
        if held is None:
            break
        shape = _shape_faults(t, m, keep, *held)
        if not shape or fit_on is not keep:
            break
        fit_on = _without(keep, shape)
    return Screen(_without(keep, shape), tuple(found + shape))


def _shape_faults(t, m, keep, r_all, sigma, field_ut) -> list[Located]:
    stuck = _stuck(t, m, keep, r_all[0], sigma)
    return stuck + _swaps(t, m, keep & _without(keep, stuck), r_all, sigma, field_ut)


def _inputs(t_s, m_ut, valid):
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    m = np.asarray(m_ut, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"m_ut must be (n, 3) µT, got shape {m.shape}")
    if len(t) != len(m):
        raise ValueError(f"t_s has {len(t)} rows but m_ut has {len(m)}")
    keep = np.all(np.isfinite(m), axis=1) & np.isfinite(t)
    if valid is not None:
        v = np.asarray(valid, dtype=bool).reshape(-1)
        if len(v) != len(m):
            raise ValueError(f"valid has {len(v)} rows but m_ut has {len(m)}")
        keep &= v
    return t, m, keep


def _without(keep: np.ndarray, found) -> np.ndarray:
    out = keep.copy()
    for x in found:
        out[x.rows] = False
    return out


def _where(t: np.ndarray, rows: np.ndarray, axis=None, gap: int = 1) -> dict:
    """Stretches [start, end] s of ``rows`` (runs broken where rows are more than ``gap`` apart)."""
    rows = np.sort(rows)
    cut = np.flatnonzero(np.diff(rows) > gap)
    starts, ends = np.r_[rows[:1], rows[cut + 1]], np.r_[rows[cut], rows[-1:]]
    out = {"time_s": [[float(t[a]), float(t[b])] for a, b in zip(starts, ends)]}
    if axis is not None:
        out["axis"] = axis
    return out


# -- timestamps ---------------------------------------------------------------------------------
# this share of samples or more repeating the time before them is a clock that ticks slower than
# the samples come (a logger stamping whole seconds repeats 90 %): the samples are sound, and the
# diagnosis takes the mean interval; a few repeats among advancing stamps are a fault
COARSE_CLOCK_SHARE = 0.2


def _timestamps(t: np.ndarray, keep: np.ndarray) -> list[Located]:
    """Samples whose time is not later than every time before them (among usable samples)."""
    idx = np.flatnonzero(keep)
    if len(idx) < 2:
        return []
    tk = t[idx]
    before = np.maximum.accumulate(tk)[:-1]
    same, back = tk[1:] == before, tk[1:] < before
    if np.mean(same) >= COARSE_CLOCK_SHARE:
        same = np.zeros_like(same)  # a clock coarser than the sample interval: its resolution, not a fault
    out = []
    for mask, name, what in ((same, "repeated_timestamps", "repeat the time of an earlier sample"),
                             (back, "out_of_order_timestamps", "go back in time")):
        rows = idx[1:][mask]
        if len(rows):
            where = _where(t, rows, gap=1)
            step = np.median(np.diff(tk)[np.diff(tk) > 0]) if np.any(np.diff(tk) > 0) else float("nan")
            summary = (f"{len(rows)} samples {what} ({len(where['time_s'])} places, first at {timewords.instant(t[rows[0]], '.3f')});"
                       " set aside")
            out.append(Located(name, Kind.FAULT, summary, where, {"n_samples": len(rows)},
                               {"median_step_s": float(step)}, rows))
    return out


# -- saturation ---------------------------------------------------------------------------------
def _saturation(t: np.ndarray, m: np.ndarray, keep: np.ndarray) -> list[Located]:
    idx = np.flatnonzero(keep)
    if len(idx) < 4 * RAIL_MIN_COUNT:
        return []
    fresh = ~repeats(m[idx])
    out = []
    for a in range(3):
        for side in (1.0, -1.0):
            hit = _rail(m[idx, a], fresh, side)
            if hit is not None:
                out.append(_rail_found(t, m, idx[hit[0]], a, side, hit[1]))
    return out


def _rail(x: np.ndarray, fresh: np.ndarray, side: float):
    """(positions at the rail, evidence) when the extreme value on ``side`` is a pile-up."""
    e = x.max() if side > 0 else x.min()
    at = x == e
    n_at = int(np.count_nonzero(at & fresh))
    inside = (~at) & fresh
    values, counts = np.unique(x[inside], return_counts=True)
    nearest = np.argsort(np.abs(values - e))[:RAIL_LEVELS]
    level = float(np.median(counts[nearest])) if len(nearest) else 0.0
    need = max(RAIL_MIN_COUNT, RAIL_MIN_SHARE * np.count_nonzero(fresh), RAIL_OVER_LEVEL * max(level, 1.0))
    if n_at < need:
        return None
    return np.flatnonzero(at), {"rail_value_ut": float(e), "n_distinct_at_rail": n_at,
                                "median_level_inside": level, "needed": float(need)}


def _outward_rails_dropped(m: np.ndarray, keep: np.ndarray, rails: list[Located]) -> list[Located]:
    """Rails whose samples lie inside the surface fitted without them: a clipped axis reads less
    than the field it cannot reach. An axis stuck at its extreme reads more and is left to the
    stuck-axis search."""
    if not rails:
        return rails
    cal = _fit(m, _without(keep, rails))
    if cal is None:
        return rails
    return [x for x in rails if np.median(_radial(cal, m[x.rows])) < 0]


def _rail_found(t, m, rows, a: int, side: float, ev: dict) -> Located:
    share = len(rows) / len(m)
    where = _where(t, rows, AXES[a], gap=2)
    end = "maximum" if side > 0 else "minimum"
    summary = (f"the {AXES[a]} axis sits at its {end} {ev['rail_value_ut']:.4g} µT in {len(rows)} samples"
               f" ({100 * share:.1f} %, {len(where['time_s'])} stretches), {ev['n_distinct_at_rail']} distinct"
               f" readings against {ev['median_level_inside']:.0f} at a typical level just inside: a clipped rail;"
               " set aside")
    return Located("saturation", Kind.FAULT, summary, where,
                   {"rail_ut": ev["rail_value_ut"], "n_samples": len(rows), "share": share}, ev, rows)


# -- the surface the rest of the data describes --------------------------------------------------
def _held_out(m: np.ndarray, keep: np.ndarray, fit_on: np.ndarray, leave_out: bool = True):
    """Each kept sample's radial residual (µT) against the surface the rest of the data
    describes, as read (row 0) and read through each of ``TRANSFORMS`` (rows 1…), nan where not
    kept; the robust scatter of the as-read residual; and the surface's field (µT). None where no
    surface fits.
    ``leave_out`` False: the faults found are already out of ``fit_on``; one fit on it."""
    idx = np.flatnonzero(keep)
    cal = _least_median(m, idx, fit_on) if leave_out else _fit(m, fit_on)
    if cal is None:
        return None
    out = np.full((len(TRANSFORMS) + 1, len(m)), np.nan)
    out[0, idx] = _radial(cal, m[idx])
    for j, (_, perm, signs) in enumerate(TRANSFORMS):
        out[j + 1, idx] = _radial(cal, m[idx][:, perm] * np.asarray(signs, float))
    r = out[0, fit_on & keep]
    return out, float(MAD_TO_SIGMA * np.median(np.abs(r - np.median(r)))), float(cal.field_ut)


def _least_median(m: np.ndarray, idx: np.ndarray, fit_on: np.ndarray) -> Calibration | None:
    """Of the fits on all of ``fit_on`` and on it without each two adjacent blocks of
    ``FIT_BLOCKS``, the one with the least median |radial residual| over the samples ``idx``."""
    if len(idx) < 20:
        return None
    best, best_med = None, np.inf
    blocks = np.array_split(np.flatnonzero(fit_on), FIT_BLOCKS)
    leave = [()] + [(k, k + 1) for k in range(FIT_BLOCKS - 1)]
    for out in leave:
        use = fit_on.copy()
        for k in out:
            use[blocks[k]] = False
        cal = _fit(m, use)
        med = float(np.median(np.abs(_radial(cal, m[idx])))) if cal is not None else np.inf
        if med < best_med:
            best, best_med = cal, med
    return best


def _fit(m: np.ndarray, use: np.ndarray) -> Calibration | None:
    idx = np.flatnonzero(use)
    if len(idx) < 20:
        return None
    res = fit_calibration(m[idx[:: max(1, len(idx) // FIT_MAX_N)]], model=FIT_MODEL, balance="none", reasons=False)
    return res.calibration if res else None


def _radial(cal: Calibration, m: np.ndarray) -> np.ndarray:
    return np.linalg.norm(cal.correct(m), axis=1) - cal.field_ut


# -- stuck axes -----------------------------------------------------------------------------------
def _quantum(x: np.ndarray) -> float:
    d = np.diff(np.unique(x))
    d = d[d > 1e-9 * max(1.0, float(np.max(np.abs(x))))]
    return float(d.min()) if len(d) else 0.0


def _stuck(t, m, keep, r0, sigma) -> list[Located]:
    idx = np.flatnonzero(keep)
    mk = m[idx]
    q = [_quantum(mk[:, a]) for a in range(3)]
    fresh = ~repeats(mk)
    out = []
    for a in range(3):
        same = np.r_[False, np.diff(mk[:, a]) == 0]
        for s, e in runs(same, STUCK_MIN_SAMPLES - 1):
            run = np.arange(s - 1, e)
            if np.count_nonzero(fresh[run]) < STUCK_MIN_SAMPLES:  # a run is counted in readings
                continue
            ev = _stuck_evidence(mk, r0[idx], run, a, q, sigma)
            if ev is not None:
                out.append(_stuck_found(t, m, idx[run], a, ev))
    return out


def _stuck_evidence(mk, rk, run, a, q, sigma):
    """Evidence that a run of one repeated value on axis ``a`` is a stuck axis, or None."""
    others = [b for b in range(3) if b != a]
    moved = float(max(np.ptp(mk[run][:, b]) for b in others))
    if any(np.ptp(mk[run][:, b]) < MOVE_QUANTA * q[b] for b in others) or moved < 2 * STUCK_OVER_FLOOR * sigma:
        return None
    if not np.all(np.isfinite(rk[run])):
        return None
    rms_in = float(np.sqrt(np.mean(rk[run] ** 2)))
    rms_out = _around(rk, run)
    if rms_in < STUCK_OVER_FLOOR * sigma or rms_in < STUCK_OVER_LOCAL * rms_out:
        return None
    return {"others_moved_ut": moved, "rms_residual_ut": rms_in, "rms_residual_around_ut": rms_out,
            "scatter_ut": sigma, "over_scatter": rms_in / sigma if sigma > 0 else float("inf")}


def _stuck_found(t, m, rows, a: int, ev: dict) -> Located:
    value = float(m[rows[0], a])
    span = float(t[rows[-1]] - t[rows[0]])
    summary = (f"the {AXES[a]} axis stuck at {value:.4g} µT for {timewords.duration(span, '.2f')} ({len(rows)} samples,"
               f" {timewords.stretch(t[rows[0]], t[rows[-1]], '.2f')}) while the other axes moved {ev['others_moved_ut']:.3g} µT;"
               f" the fitted surface misses those samples by {ev['rms_residual_ut']:.3g} µT RMS,"
               f" {ev['over_scatter']:.1f}× the recording's scatter; set aside")
    where = {"time_s": [[float(t[rows[0]]), float(t[rows[-1]])]], "axis": AXES[a]}
    return Located("stuck_axis", Kind.FAULT, summary, where,
                   {"value_ut": value, "duration_s": span, "n_samples": len(rows)}, ev, rows)


# -- swapped or flipped axes ---------------------------------------------------------------------
def _swaps(t, m, keep, r_all, sigma, field_ut) -> list[Located]:
    """Runs of samples each far off the surface as read and on it transformed; then stretches
    the total evidence (magcal.diagnose.locate.swap_evidence) finds, where they add to these."""
    if not sigma > 0:
        return []
    found = _favoured_swaps(t, keep, r_all, sigma)
    for x in _strongest_per_stretch(_evidence_swaps(t, m, keep, r_all, sigma, field_ut)):
        hit = [y for y in found if np.intersect1d(x.rows, y.rows).size]
        if all(_widens(x, y) for y in hit):  # none, or runs of the same reading it holds whole
            found = [y for y in found if not any(y is h for h in hit)] + [x]
    return found


def _widens(x: Located, y: Located) -> bool:
    """``x`` reads its stretch as ``y`` does and holds every sample of it: the run of samples
    each far off the surface is the core of a swap whose ends the total evidence places."""
    return x.params["reading"] == y.params["reading"] and np.isin(y.rows, x.rows).all()


def _favoured_swaps(t, keep, r_all, sigma) -> list[Located]:
    idx = np.flatnonzero(keep)
    a0 = np.abs(r_all[0, idx])
    out = []
    for j, (name, perm, signs) in enumerate(TRANSFORMS):
        at = np.abs(r_all[j + 1, idx])
        favour = (a0 > SWAP_MISS * sigma) & (at < SWAP_FIT * sigma)
        against = (a0 < SWAP_FIT * sigma) & (at > SWAP_MISS * sigma)
        for run in _favoured_runs(favour, against):
            if np.count_nonzero(favour[run]) >= SWAP_MIN_SAMPLES:
                x = _swap_found(t, idx[run], name, perm, signs, a0[run], at[run], sigma, _around(a0, run))
                if _swap_holds(x.evidence):
                    out.append(x)
    return _strongest_per_stretch(out)


def _around(a: np.ndarray, run: np.ndarray) -> float:
    """RMS of ``a`` over the 2·len(run) samples on each side of ``run``."""
    k = len(run)
    around = np.r_[np.arange(max(0, run[0] - 2 * k), run[0]), np.arange(run[-1] + 1, min(len(a), run[-1] + 1 + 2 * k))]
    return float(np.sqrt(np.mean(a[around] ** 2))) if len(around) else 0.0


def _favoured_runs(favour: np.ndarray, against: np.ndarray) -> list[np.ndarray]:
    """Runs of favoured samples joined across samples that are neither (as read and transformed
    both miss, or both fit: a swap leaves the points where the surface meets its mirror image on
    it) but never across one that fits as read and misses transformed."""
    state = np.where(favour, 1, np.where(against, -1, 0))
    out = []
    for s, e in runs(state >= 0):
        inside = s + np.flatnonzero(state[s:e] == 1)
        if len(inside):
            out.append(np.arange(inside[0], inside[-1] + 1))
    return out


def _swap_holds(ev: dict) -> bool:
    rms0, rmst = ev["rms_as_read_ut"], ev["rms_as_transformed_ut"]
    return rms0 >= SWAP_RATIO * rmst and rms0 >= SWAP_OVER_LOCAL * ev["rms_around_ut"]


def _swap_found(t, rows, name, perm, signs, a0, at, sigma, rms_around, stretch=None) -> Located:
    span = [float(t[rows[0]]), float(t[rows[-1]])]
    rms0, rmst = float(np.sqrt(np.mean(a0 ** 2))), float(np.sqrt(np.mean(at ** 2)))
    summary = (f"{len(rows)} samples ({timewords.stretch(*span, '.2f')}) fit the surface of the rest of the recording"
               f" read as {name} ({rmst:.3g} µT RMS) but not as recorded ({rms0:.3g} µT RMS,"
               f" {rms0 / sigma:.1f}× the recording's scatter): axes swapped or flipped; set aside")
    evidence = {"rms_as_read_ut": rms0, "rms_as_transformed_ut": rmst, "scatter_ut": sigma, "rms_around_ut": rms_around}
    if stretch is not None:
        evidence |= {"view": stretch.view.value, "evidence_nats": stretch.evidence, "threshold_nats": stretch.threshold}
    if stretch is not None and stretch.view is swap_evidence.View.EDGES:
        evidence |= {"jumps_ut": list(stretch.jumps), "typical_step_ut": stretch.typical_step}
        summary = (f"the readings jump by {stretch.jumps[0]:.3g} and {stretch.jumps[1]:.3g} µT into and out of"
                   f" {len(rows)} samples ({timewords.stretch(*span, '.2f')}), against a typical step of"
                   f" {stretch.typical_step:.3g} µT there; read as {name} both ends are ordinary steps"
                   f" ({stretch.evidence:.0f} nats of evidence): axes swapped or flipped; set aside")
    axes = [AXES[i] for i in range(3) if perm[i] != i or signs[i] < 0]
    return Located("axis_swap", Kind.FAULT, summary, {"time_s": [span], "axis": axes},
                   {"reading": name, "permutation": list(perm), "signs": list(signs), "n_samples": len(rows)},
                   evidence, rows)


def _strongest_per_stretch(found: list[Located]) -> list[Located]:
    """Where two readings claim overlapping samples, the one that fits them better stands."""
    order = sorted(found, key=lambda x: x.evidence["rms_as_transformed_ut"] / x.evidence["rms_as_read_ut"])
    out, taken = [], np.zeros(0, np.int64)
    for x in order:
        if not np.intersect1d(x.rows, taken).size:
            out.append(x)
            taken = np.r_[taken, x.rows]
    return out


def _evidence_swaps(t, m, keep, r_all, sigma, field_ut) -> list[Located]:
    """Stretches whose total evidence, radial or at their two ends, says they were transformed
    (over the fresh readings: a repeated read is one conversion). A radial claim must also pass
    the contrast of ``_swap_holds``: a surface that misses a stretch a little less when it is
    transformed is misfit, not a swap."""
    idx = np.flatnonzero(keep)
    fresh = idx[~repeats(m[idx])]
    if len(fresh) < 20:
        return []
    pos = np.searchsorted(idx, fresh)
    a0 = np.abs(r_all[0, idx])
    found = swap_evidence.radial(r_all[:, fresh], sigma)
    found += swap_evidence.edges(m[fresh], [(p, g) for _, p, g in TRANSFORMS], field_ut)
    out = []
    for st in found:
        end = pos[st.last + 1] if st.last + 1 < len(pos) else len(idx)
        run = np.arange(pos[st.first], end)
        name, perm, signs = TRANSFORMS[st.transform]
        x = _swap_found(t, idx[run], name, perm, signs, a0[run], np.abs(r_all[st.transform + 1, idx[run]]),
                        sigma, _around(a0, run), st)
        if st.view is swap_evidence.View.EDGES or _swap_holds(x.evidence):
            out.append(x)
    return out


# -- the table's rows ----------------------------------------------------------------------------
FAULT_NAMES = ("stuck_axis", "saturation", "axis_swap", "repeated_timestamps", "out_of_order_timestamps")


def _search_for(name: str):
    def search(res: Residual) -> tuple[Located, ...]:
        return tuple(x for x in screen(res.t_s, res.m_ut).found if x.effect == name)
    search.__name__ = f"search_{name}"
    return search


EFFECTS: tuple[Effect, ...] = tuple(Effect(name, Kind.FAULT, _search_for(name)) for name in FAULT_NAMES)

__all__ = ["EFFECTS", "FAULT_NAMES", "Screen", "TRANSFORMS", "screen"]
