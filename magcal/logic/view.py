"""What the live 3-D view shows of a calibration, as plain values (pure: session in, state out).

The browser page (``magcal calibrate --view``, ``magcal run --view``) draws the state made here
and nothing else, so every number on it is computed — and tested — in this module:

- the kept samples as points on the unit sphere (corrected by the live calibration, divided by
  its field), the field's direction now, and the 128 equal-area direction cells with their
  counts (an empty cell is a gap drawn on the sphere);
- the four numbers MotionCal users read, in percent: ``gaps`` (share of the direction cells
  holding no sample), ``variance`` (spread of the corrected magnitude about its mean),
  ``wobble`` (how far off the fitted centre the corrected cloud still sits: the shift along
  which its radius grows, by least squares, over the field) and ``fit error`` (rms of the
  corrected magnitude about the fitted field);
- magcal's own: the live offset with its 1σ, the field, the coverage against the gate, and
  every gate the write waits on;
- which way to turn next: the side of the board to aim along the Earth's field to reach the
  nearest empty cell, and how far that is;
- where the write stands, ending in VERIFIED (or why not).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from ..fit.coverage import cell_centres, nearest_empty_cell, side_name
from .session import Session, Status

MAX_POINTS = 2048  # the page draws at most this many points (the kept set holds 1024)


class WriteState(str, Enum):
    """Where writing the calibration stands, as the page shows it."""

    PENDING = "pending"  # still collecting or solving
    WRITING = "writing"
    VERIFIED = "verified"  # written and read back equal
    NOT_VERIFIED = "not verified"  # written, but the read-back differed or failed
    NOT_WRITTEN = "not written"  # the fit passed; writing was not asked for or not possible
    FAILED = "failed"  # no calibration: a gate was not met, the fit failed, the write refused


@dataclass(frozen=True)
class MotionCalNumbers:
    """The four numbers of PJRC MotionCal, in percent (None until there is a calibration)."""

    gaps_pct: float
    variance_pct: float | None
    wobble_pct: float | None
    fit_error_pct: float | None


@dataclass(frozen=True)
class Turn:
    """The next move: aim the board's ``side`` along the field (``target``, a unit vector in
    the sensor frame), ``angle_deg`` from where the field points now (``here``)."""

    side: str
    target: tuple
    angle_deg: float | None
    here: tuple | None


@dataclass(frozen=True)
class ViewState:
    """Everything the page draws, JSON-ready through ``to_dict``."""

    status: str
    write: WriteState
    message: str
    samples: int
    kept: int
    rate_hz: float | None
    time_left_s: float | None
    points: list
    cells: list
    bands: int
    sectors: int
    per_cell: int
    motioncal: MotionCalNumbers
    live: dict
    gates: list
    waiting_on: list
    turn: Turn | None
    held: dict | None = None  # the calibration this command last wrote and verified (``run``)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["write"] = self.write.value
        d["motioncal"] = self.motioncal.__dict__.copy()
        d["turn"] = None if self.turn is None else self.turn.__dict__.copy()
        return d


def _r(x, digits: int = 3):
    """A float for JSON: rounded, and None when it is not finite."""
    if x is None:
        return None
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def _unit(v) -> np.ndarray | None:
    if v is None:
        return None
    v = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(v))
    return v / n if n > 0 and math.isfinite(n) else None


def motioncal_numbers(field_ut, calibration, counts, bands: int, sectors: int) -> MotionCalNumbers:
    """MotionCal's four quality numbers for samples ``field_ut`` (n, 3) under ``calibration``
    (None: only the gaps are known). ``counts``: samples per direction cell."""
    counts = np.asarray(counts)
    gaps = 100.0 * float(np.count_nonzero(counts == 0)) / len(counts)
    m = np.atleast_2d(np.asarray(field_ut, dtype=np.float64))
    if calibration is None or len(m) < 4:
        return MotionCalNumbers(round(gaps, 1), None, None, None)
    h = calibration.correct(m)
    r = np.linalg.norm(h, axis=1)
    b = calibration.field_ut
    variance = 100.0 * float(np.std(r)) / float(np.mean(r))
    fit_error = 100.0 * float(np.sqrt(np.mean((r - b) ** 2))) / b
    # a cloud shifted by c from the centre has radius ≈ a + u·c along each direction u
    design = np.column_stack([np.ones(len(r)), h / r[:, None]])
    coef, *_ = np.linalg.lstsq(design, r, rcond=None)
    wobble = 100.0 * float(np.linalg.norm(coef[1:])) / b
    return MotionCalNumbers(round(gaps, 1), _r(variance, 2), _r(wobble, 2), _r(fit_error, 2))


def next_turn(counts, bands: int, sectors: int, here) -> Turn | None:
    """The empty direction cell nearest to where the field points now (``here``, any vector or
    None), as the side of the board to aim along the field; None when no cell is empty."""
    u = _unit(here)
    found = nearest_empty_cell(counts, bands, sectors, u)
    if found is None:
        return None
    cell, angle = found
    target = cell_centres(bands, sectors)[cell]
    return Turn(side=side_name(target), target=tuple(_r(v) for v in target),
                angle_deg=None if u is None else _r(angle, 1),
                here=None if u is None else tuple(_r(v) for v in u))


def write_state(session: Session, written: bool | None, verified: bool | None) -> WriteState:
    """The write as the page shows it, from the session's stage and the outcome once known."""
    s = session.status
    if s is Status.FAILED:
        return WriteState.NOT_VERIFIED if written else WriteState.FAILED
    if s is Status.DONE:
        if verified:
            return WriteState.VERIFIED
        return WriteState.NOT_VERIFIED if written else WriteState.NOT_WRITTEN
    if s in (Status.WRITING, Status.VERIFYING):
        return WriteState.WRITING
    return WriteState.PENDING


def _points(session: Session, calibration) -> list:
    """The kept samples on the unit sphere: corrected and divided by the field when there is a
    live calibration (a good one puts them on the sphere); before one, their directions about
    the kept set's centre — the directions the coverage cells count."""
    m = session.kept.field_ut[:MAX_POINTS]
    if len(m) == 0:
        return []
    if calibration is not None:
        p = calibration.correct(m) / calibration.field_ut
    else:
        d = m - session.kept.centre_ut
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        p = d / np.where(norm > 0, norm, 1.0)
    return np.round(p, 3).tolist()


def _live(session: Session, calibration, estimate) -> dict:
    """magcal's own live numbers: offset ± 1σ, field, noise, coverage and what it needs (after
    the final fit, its offset and 1σ)."""
    sigma = None if estimate is None else [_r(v) for v in estimate.offset_sigma_ut]
    if session.result:
        sigma = [_r(v) for v in session.result.uncertainty["offset_ut"]]
    return {
        "model": None if estimate is None else estimate.model,
        "offset_ut": None if calibration is None else [_r(v, 2) for v in calibration.offset_ut],
        "offset_sigma_ut": sigma,
        "field_ut": None if calibration is None else _r(calibration.field_ut, 2),
        "noise_ut": None if estimate is None else _r(estimate.noise_ut),
        "coverage": _r(session.kept.coverage(), 4),
        "coverage_needed": _r(session.gates_cfg.min_coverage, 4),
    }


def _final_calibration(session: Session):
    """After the final fit: its calibration (what is written), else the live one."""
    if session.result:
        return session.result.calibration
    est = session.tracker.estimate
    return None if est is None else est.calibration


def page_state(session: Session, *, elapsed_s: float = 0.0, timeout_s: float | None = None,
               written: bool | None = None, verified: bool | None = None, held=None) -> ViewState:
    """The page's state for ``session`` now (``elapsed_s`` on the caller's clock since
    collecting began; ``written``/``verified``: the outcome, once known; ``held``: the
    ``Calibration`` this command last wrote and verified, when it goes on collecting after it)."""
    kept = session.kept
    estimate = session.tracker.estimate
    calibration = _final_calibration(session)
    counts = kept.cell_counts()
    collecting = session.status is Status.COLLECTING
    gates = session.final_gates if session.result else session.live_gates()
    here = None if session.last_field_ut is None else session.last_field_ut - kept.centre_ut
    n = int(session.counters["samples_in"])
    left = None if timeout_s is None or not collecting else _r(max(0.0, timeout_s - elapsed_s), 1)
    return ViewState(
        status=session.status.value, write=write_state(session, written, verified),
        message=session.failure_message, samples=n, kept=len(kept),
        rate_hz=_r(n / elapsed_s, 1) if elapsed_s > 0.5 else None, time_left_s=left,
        points=_points(session, calibration), cells=[int(c) for c in counts],
        bands=kept.bands, sectors=kept.sectors, per_cell=kept.per_cell,
        motioncal=motioncal_numbers(kept.field_ut, calibration, counts, kept.bands, kept.sectors),
        live=_live(session, calibration, estimate),
        gates=[{"gate": g.name, "passed": g.passed, "message": g.message} for g in gates],
        waiting_on=[g.name for g in gates if not g.passed],
        turn=next_turn(counts, kept.bands, kept.sectors, here) if collecting else None,
        held=None if held is None else {"offset_ut": [_r(v, 2) for v in held.offset_ut],
                                        "field_ut": _r(held.field_ut, 2), "verified": True},
    )
