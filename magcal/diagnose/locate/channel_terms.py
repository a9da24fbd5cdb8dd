"""The forms a logged channel can take in the offset, and the offset term each one adds.

A located channel term is stored in ``Located.params`` with its ``form`` (a ``Form`` value) and
what that form needs; ``term_ut`` turns those params and the channel back into the (n, 3) µT
the term adds to the raw samples, relative to the channel's reference value.
"""

from __future__ import annotations

from enum import Enum
from typing import Mapping

import numpy as np
from scipy.signal import lfilter

ANGLE_UNITS = ("deg", "rad")


class Form(Enum):
    """How a channel enters the measured field."""

    OFFSET_DELAY = "offset_delay"  # β·c(t − lag), lag ≥ 0
    OFFSET_FIRST_ORDER = "offset_first_order"  # β·(c through a first-order lag τ)
    GAIN = "gain"  # |h| ∝ 1 + g·Δc, the same on every axis
    AXIS_GAIN = "axis_gain"  # the scale of axis k ∝ 1 + g_k·Δc
    SQUARE = "square"  # β₁·Δc + β₂·Δc²
    STEP = "step"  # β·[c > threshold]
    ANGLE = "angle"  # v₁ cos c + v₂ sin c


N_LAGS = 24  # lags / time constants on the geometric grid (plus 0 for the delay)
MAX_LAG_SHARE = 1.0 / 6.0  # the longest lag tried, as a share of the recording's span
MIN_LAG_SAMPLES = 0.25  # the shortest, in sample periods
EVEN_CLOCK = 0.01  # intervals within this share of their median are one clock


def sample_period_s(t_s: np.ndarray) -> float:
    """The typical interval between samples that differ in time (s): a clock that ticks more
    coarsely than the samples arrive (a log's whole-second time column at 10 Hz) repeats most
    times, and the median of every interval would be 0. 1 s where no two times differ."""
    steps = np.diff(np.asarray(t_s, np.float64))
    steps = steps[steps > 0]
    return float(np.median(steps)) if steps.size else 1.0


def lag_grid(t_s: np.ndarray) -> np.ndarray:
    """Lags and time constants tried (s): a quarter of a sample period to a sixth of the span —
    a slowly sampled log (1.2 Hz) still shows a 0.4 s lag as a smaller first step at each switch."""
    dt = sample_period_s(t_s)
    top = max(float(np.ptp(t_s)) * MAX_LAG_SHARE, 3 * dt)
    return np.geomspace(MIN_LAG_SAMPLES * dt, top, N_LAGS)


def delayed(c: np.ndarray, t_s: np.ndarray, lag_s: float) -> np.ndarray:
    """c(t − lag), held at its first value before the start."""
    return np.interp(t_s - lag_s, t_s, c)


def low_passed(c: np.ndarray, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """c through a first-order lag, y_i = a_i·y_(i−1) + (1 − a_i)·c_i with a_i = exp(−Δt_i/τ) at
    each sample's own interval, started settled: a log whose samples come in bursts (a few ms,
    then 60 ms) has its time constant in seconds, not in samples."""
    t = np.asarray(t_s, np.float64)
    c = np.asarray(c, np.float64)
    dt = np.diff(t)
    med = float(np.median(dt))
    if np.all(np.abs(dt - med) <= EVEN_CLOCK * med):  # an even clock: one filter at its period
        a = 1.0 - np.exp(-med / tau_s)
        y, _ = lfilter([a], [1.0, a - 1.0], c, zi=[(1.0 - a) * c[0]])
        return y
    return _varying_lag(c, np.minimum(np.maximum(dt, 0.0) / tau_s, STEP_DECAY))


MAX_DECAY = 600.0  # a stretch of the uneven-clock filter spans at most this many time constants (e^600 is finite)
STEP_DECAY = 37.0  # … and one step at most this many: e^(−37) is below float64's resolution of 1


def _varying_lag(c: np.ndarray, decay: np.ndarray) -> np.ndarray:
    """y_0 = c_0, y_i = a_i·y_(i−1) + (1 − a_i)·c_i with a_i = exp(−decay_(i−1)), in closed form
    per stretch: y_i = e^(−D_i)·(y_start + Σ_k (1 − a_k)·c_k·e^(D_k)), D the decay summed from
    the stretch's start (at most MAX_DECAY, so e^(D) stays finite) — vectorised, where a loop
    over the samples cost 3–4 ms per lag on an 8000-sample log."""
    y = np.empty_like(c)
    y[0] = c[0]
    total = np.concatenate([[0.0], np.cumsum(decay)])
    start = 1
    while start < len(c):
        stop = max(int(np.searchsorted(total, total[start - 1] + MAX_DECAY, side="right")), start + 1)
        stop = min(stop, len(c))
        d = total[start:stop] - total[start - 1]
        w = -np.expm1(-decay[start - 1 : stop - 1]) * c[start:stop] * np.exp(d)
        y[start:stop] = np.exp(-d) * (y[start - 1] + np.cumsum(w))
        start = stop
    return y


def angle_scale(unit_code: float) -> float:
    """Radians per unit of an angle channel in ``ANGLE_UNITS[unit_code]``."""
    return np.pi / 180.0 if ANGLE_UNITS[int(unit_code)] == "deg" else 1.0


def term_ut(form: Form, p: Mapping, c: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """The offset (n, 3) µT an offset-type term adds, as f(c) − f(reference)."""
    ref = float(p["reference"])
    if form is Form.OFFSET_DELAY:
        return np.outer(delayed(c, t_s, float(p.get("lag_s") or 0.0)) - ref, p["coef_ut_per_unit"])
    if form is Form.OFFSET_FIRST_ORDER:
        lag = float(p.get("lag_s") or 0.0)
        x = low_passed(c, t_s, lag) if lag > 0 else c
        return np.outer(x - ref, p["coef_ut_per_unit"])
    if form is Form.SQUARE:
        mu = float(p["mean"])
        lin, sq = np.asarray(p["coef_ut_per_unit"]), np.asarray(p["coef_ut_per_unit2"])
        return np.outer(c - ref, lin) + np.outer((c - mu) ** 2 - (ref - mu) ** 2, sq)
    if form is Form.STEP:
        thr = float(p["threshold"])
        return np.outer((c > thr).astype(np.float64) - float(ref > thr), p["step_ut"])
    if form is Form.ANGLE:
        s = angle_scale(ANGLE_UNITS.index(p["angle_unit"]))
        cos = np.cos(c * s) - np.cos(ref * s)
        sin = np.sin(c * s) - np.sin(ref * s)
        return np.outer(cos, p["cos_ut"]) + np.outer(sin, p["sin_ut"])
    raise ValueError(f"{form.value} is a gain, not an offset term")
