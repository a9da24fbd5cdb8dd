"""What every figure of the report draws from, computed once from a diagnosis: times relative
to the start (in a readable unit), residuals before and after, field magnitudes, directions,
which samples were set aside, and a thinned index for scatter plots."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...diagnose import channels as ch
from ...diagnose.diagnosis import reported_calibration

MAX_POINTS = 20000


def time_unit(span_s: float, clock: bool = True) -> tuple[str, float]:
    """(unit name, seconds per unit) for a recording ``span_s`` long: s, min or h; a recording
    without a clock is counted in samples (its t_s is the sample index)."""
    if not clock:
        return "samples", 1.0
    if span_s < 300:
        return "s", 1.0
    if span_s < 3 * 3600:
        return "min", 60.0
    return "h", 3600.0


def thin(n: int, most: int = MAX_POINTS) -> np.ndarray:
    """At most ``most`` evenly spread indices of ``n`` (time order kept)."""
    return np.arange(n) if n <= most else np.linspace(0, n - 1, most).astype(int)


@dataclass(frozen=True)
class Views:
    t: np.ndarray  # time since the first sample, in ``t_unit``
    t_unit: str
    t_scale_s: float  # seconds per t unit
    clock: bool  # False: t counts samples (the recording has no time)
    t_axis: str  # what t is, for an axis label: time since the first sample, or the sample number
    before: np.ndarray  # radial residual of the sphere (µT)
    after: np.ndarray  # of the final model (µT)
    raw_norm: np.ndarray  # |m| as recorded (µT)
    sphere_norm: np.ndarray  # |m − b| with the sphere's offset b
    final_norm: np.ndarray  # |calibrated| with the final model, as the JSON's calibration corrects
    field_ut: float  # the calibration's field, as the JSON states it (µT)
    u: np.ndarray  # direction of the calibrated field (unit vectors, sensor frame)
    h: np.ndarray  # the calibrated field (µT)
    chans: dict  # channels, time (t_s) among them, as the final model takes them
    good: np.ndarray  # not set aside as a glitch
    idx: np.ndarray  # thinned indices for scatter plots


def views_of(diagnosis) -> Views:
    s = diagnosis.series
    chans = dict(s.channels)
    chans[ch.TIME] = s.t_s
    before = diagnosis.baseline.residual(s.field_ut, {})
    m = diagnosis.modelled_field_ut()  # with the effects the locate step modelled removed
    after = diagnosis.final.residual(m, chans)
    cal = reported_calibration(diagnosis.final)  # the calibration the table and the JSON state
    h = cal.correct(m, {c: chans[c] for c in diagnosis.final.spec.channels})
    norm = np.linalg.norm(h, axis=1)
    span = float(s.t_s[-1] - s.t_s[0]) if len(s) else 0.0
    unit, scale = time_unit(span, s.clock)
    return Views(
        t=(s.t_s - s.t_s[0]) / scale if len(s) else s.t_s,
        t_unit=unit,
        t_scale_s=scale,
        clock=s.clock,
        t_axis=f"time since the first sample ({unit})" if s.clock else "sample number (the recording has no time)",
        before=before,
        after=after,
        raw_norm=np.linalg.norm(s.field_ut, axis=1),
        sphere_norm=np.linalg.norm(s.field_ut - diagnosis.baseline.offset_ut, axis=1),
        final_norm=norm,
        field_ut=cal.field_ut,
        u=h / np.where(norm > 0, norm, 1.0)[:, None],
        h=h,
        chans=chans,
        good=~diagnosis.outlier_mask,
        idx=thin(len(s)),
    )


def running_mean(x: np.ndarray, y: np.ndarray, bins: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Mean of y over equal-count stretches of x (x sorted first)."""
    order = np.argsort(x, kind="stable")
    xs, ys = x[order], y[order]
    edges = np.linspace(0, len(xs), bins + 1).astype(int)
    pairs = [(xs[a:b].mean(), ys[a:b].mean()) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    return (np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])) if pairs else (np.zeros(0),) * 2


def binned(x: np.ndarray, y: np.ndarray, bins: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Mean of y within equal-count ranges of x (an on/off channel: equal-width ranges)."""
    if len(x) == 0:
        return np.zeros(0), np.zeros(0)
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 5 and np.ptp(x) > 0:
        edges = np.linspace(x.min(), x.max(), 9)
    if len(edges) < 2:
        return np.array([x.mean()]), np.array([y.mean()])
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    cs, ms = [], []
    for b in range(len(edges) - 1):
        sel = which == b
        if sel.sum() >= 5:
            cs.append(x[sel].mean())
            ms.append(y[sel].mean())
    return np.array(cs), np.array(ms)


def symmetric_limit(*arrays, q: float = 99.5, floor: float = 0.05) -> float:
    """A y-range half-width that holds the bulk of every array (its q-th percentile of |value|)."""
    vals = [np.percentile(np.abs(a), q) for a in arrays if len(a)]
    return max(max(vals) if vals else 0.0, floor)
