"""What a found channel term says: its name, where, its coefficients with 95 % intervals, and one
plain sentence with the numbers (see ``channel_forms``)."""

from __future__ import annotations

import numpy as np

from .. import channels as catalogue
from .. import timewords
from . import channel_scores as cs
from .base import Kind, Located, Residual
from .channel_terms import ANGLE_UNITS, Form, lag_grid, term_ut

MAX_PROFILE = 12  # at most this many candidates of the 95 % lag profile are widened over
GAIN_EFFECT = {catalogue.TEMP: "temperature_gain"}
OFFSET_EFFECT = {catalogue.TEMP: "temperature_drift", catalogue.CURRENT: "current_interference"}


def reference(name: str, c: np.ndarray) -> float:
    """The channel value the calibration is taken at: 0 A for a current, else the value at the
    end of the recording (the mean of its last 2 %)."""
    if name == catalogue.CURRENT:
        return 0.0
    return float(np.mean(c[-max(len(c) // 50, 1):]))


def intervals(fr: cs.Frame, pick: cs.Pick) -> dict:
    """Coefficients at the best candidate and their 95 % intervals, per component and for the
    magnitude of each 3-vector block, widened over the candidates in the 95 % profile (for a lag
    family: the lag's own uncertainty)."""
    beta, cov, infl = _fit_at(fr, pick, pick.j)
    lagged = pick.fam.form in (Form.OFFSET_DELAY, Form.OFFSET_FIRST_ORDER)
    s2 = _s2_after(fr, pick)
    near = cs.profile(pick.ess, pick.j, s2, infl) if lagged else np.array([pick.j])
    # a lag is stated only when no lag fits clearly worse (χ²₁ at 0.1 %, with the inflation)
    lag_zero_fits = bool(lagged and pick.ess[0] >= pick.ess[pick.j] - cs.CHI2_1_999 * s2 * infl)
    near = near[np.argsort(-pick.ess[near])][:MAX_PROFILE]
    lo, hi = beta.copy(), beta.copy()
    mag_lo, mag_hi = _mags(beta), _mags(beta)
    for jj in near:
        b, v, _ = _fit_at(fr, pick, int(jj))
        se = np.sqrt(np.maximum(np.diag(v), 0.0))
        lo, hi = np.minimum(lo, b - cs.T_975_19 * se), np.maximum(hi, b + cs.T_975_19 * se)
        m, sm = _mags(b), _mag_se(b, v)
        mag_lo, mag_hi = np.minimum(mag_lo, m - cs.T_975_19 * sm), np.maximum(mag_hi, m + cs.T_975_19 * sm)
    values = pick.fam.values[near]
    return {"beta": beta, "lo": lo, "hi": hi, "mag_lo": np.maximum(mag_lo, 0.0), "mag_hi": mag_hi,
            "inflation": infl, "values": values, "lag_zero_fits": lag_zero_fits}


def _fit_at(fr: cs.Frame, pick: cs.Pick, j: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(coefficients, covariance, inflation) of candidate j: from the whitened fit where the
    pick has one (a lag, ``channel_whiten``), else from the frame's own."""
    if pick.white is not None:
        return pick.white.hac_cov(pick.fam.series[:, j, 0])
    return cs.hac_cov(fr, pick.fam, j)


def _s2_after(fr: cs.Frame, pick: cs.Pick) -> float:
    """The residual variance left after the pick's fit, on the scale its ESS were taken."""
    if pick.white is not None:
        return pick.white.s2_after(float(pick.ess[pick.j]))
    return fr.s2_after(pick.ess[pick.j], cs.n_columns(pick.fam))


def _mags(b: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm(b[i:i + 3]) for i in range(0, len(b), 3)])


def _mag_se(b: np.ndarray, v: np.ndarray) -> np.ndarray:
    out = []
    for i in range(0, len(b), 3):
        blk = b[i:i + 3]
        d = blk / max(np.linalg.norm(blk), 1e-300)
        out.append(float(np.sqrt(max(d @ v[i:i + 3, i:i + 3] @ d, 0.0))))
    return np.array(out)


def describe(res: Residual, fr: cs.Frame, pick: cs.Pick, c: np.ndarray, evidence: dict) -> Located:
    """The Located of a significant pick."""
    name = pick.fam.channel
    iv = intervals(fr, pick)
    ev = dict(evidence, hac_inflation=iv["inflation"], floor_ut=res.floor_ut)
    p = {"channel": name, "form": pick.fam.form.value, "reference": reference(name, c), "mean": float(np.mean(c))}
    form = pick.fam.form
    if form in (Form.GAIN, Form.AXIS_GAIN):
        return _gain(res, pick, iv, p, c, ev)
    if form in (Form.OFFSET_DELAY, Form.OFFSET_FIRST_ORDER):
        return _lagged(res, pick, iv, p, c, ev)
    return _shaped(res, pick, iv, p, c, ev)


def _size(res: Residual, form: Form, p: dict, c: np.ndarray) -> float:
    """The largest offset (µT) the term adds over the recording, relative to the reference."""
    return float(np.max(np.linalg.norm(term_ut(form, p, c, np.asarray(res.t_s, np.float64)), axis=1)))


def _vec(v) -> str:
    return "(" + ", ".join(f"{x:+.3g}" for x in v) + ")"


def _unit(name: str) -> str:
    return catalogue.unit_of(name)


def _lagged(res, pick, iv, p, c, ev) -> Located:
    name, form, j = pick.fam.channel, pick.fam.form, pick.j
    beta = iv["beta"]
    values = pick.fam.values
    lag = float(values[j])
    at_edge = lag >= 0.999 * lag_grid(np.asarray(res.t_s, np.float64))[-1]
    resolved = not at_edge and lag > 0 and not iv["lag_zero_fits"]
    p.update(coef_ut_per_unit=beta, coef_low_ut_per_unit=iv["lo"], coef_high_ut_per_unit=iv["hi"],
             coef_magnitude_ut_per_unit=float(np.linalg.norm(beta)),
             coef_magnitude_interval=[float(iv["mag_lo"][0]), float(iv["mag_hi"][0])],
             lag_kind="delay" if form is Form.OFFSET_DELAY else "first_order", lag_s=lag)
    if resolved:
        p["lag_interval_s"] = [float(np.min(iv["values"])), float(np.max(iv["values"]))]
    if at_edge:
        ev["lag_beyond_search_s"] = lag
        p["lag_s"] = lag
    size = _size(res, form, p, c)
    unit = _unit(name)
    where = {"channel": name, "direction": beta / max(np.linalg.norm(beta), 1e-300)}
    kind = "a delay" if form is Form.OFFSET_DELAY else "a first-order lag"
    if resolved:
        where["lag_s"] = lag
        lo, hi = p["lag_interval_s"]
        how = f"through {kind} of {timewords.duration(lag, '.3g')} ({timewords.duration_range(lo, hi, '.3g')})"
    elif at_edge:
        how = f"through a lag of {timewords.duration(lag, '.3g')} or longer (the longest tried, so not stated as a lag)"
    else:
        how = "with no lag"
    mlo, mhi = p["coef_magnitude_interval"]
    summary = (f"The offset follows {name} {how}: {np.linalg.norm(beta):.3g} µT/{unit} (95 %: {mlo:.3g}–{mhi:.3g}) "
               f"along {_vec(where['direction'])}, up to {size:.3g} µT, {size / max(res.floor_ut, 1e-300):.1f}× the "
               f"recording's floor.")
    effect = "lagged_channel" if resolved or at_edge else OFFSET_EFFECT.get(name, "channel_offset")
    ev["size_ut"] = size
    return Located(effect, Kind.PHYSICS, summary, where, p, ev)


def _gain(res, pick, iv, p, c, ev) -> Located:
    name = pick.fam.channel
    g = iv["beta"]
    p.update(gain_per_unit=g, gain_pct_per_unit=100.0 * g, gain_low_pct_per_unit=100.0 * iv["lo"],
             gain_high_pct_per_unit=100.0 * iv["hi"], center_ut=np.asarray(res.calibration.offset_ut))
    unit = _unit(name)
    size = float(np.max(np.abs(c - p["reference"])) * np.max(np.abs(g)) * res.calibration.field_ut)
    if pick.fam.form is Form.GAIN:
        what = (f"{100 * g[0]:+.3g} %/{unit} (95 %: {100 * iv['lo'][0]:+.3g} to {100 * iv['hi'][0]:+.3g}) "
                f"on every axis")
        where = {"channel": name}
    else:
        what = f"{_vec(100 * g)} %/{unit} on the x, y, z axes"
        where = {"channel": name, "axis": [a for a, v in zip("xyz", np.abs(g)) if v >= 0.5 * np.max(np.abs(g))]}
    summary = (f"The sensor's gain changes with {name} by {what}: up to {size:.3g} µT of field, "
               f"{size / max(res.floor_ut, 1e-300):.1f}× the recording's floor, which no offset can follow.")
    ev["size_ut"] = size
    return Located(GAIN_EFFECT.get(name, "channel_gain"), Kind.PHYSICS, summary, where, p, ev)


def _shaped(res, pick, iv, p, c, ev) -> Located:
    name, form, beta = pick.fam.channel, pick.fam.form, iv["beta"]
    unit = _unit(name)
    if form is Form.SQUARE:
        p.update(coef_ut_per_unit=beta[:3], coef_ut_per_unit2=beta[3:], coef_low=iv["lo"], coef_high=iv["hi"])
        what = f"as a curve: {_vec(beta[:3])} µT/{unit} and {_vec(beta[3:])} µT/{unit}² about {p['mean']:.3g}"
        effect = "channel_square"
    elif form is Form.STEP:
        p.update(threshold=float(pick.fam.values[pick.j]), step_ut=beta, step_low_ut=iv["lo"], step_high_ut=iv["hi"])
        what = f"as a step of {_vec(beta)} µT where it passes {p['threshold']:.4g} {unit}"
        effect = "channel_step"
    else:
        p.update(angle_unit=ANGLE_UNITS[pick.j], cos_ut=beta[:3], sin_ut=beta[3:], coef_low=iv["lo"], coef_high=iv["hi"])
        what = (f"as an arm turned by it (read in {p['angle_unit']}): {_vec(beta[:3])} µT·cos + "
                f"{_vec(beta[3:])} µT·sin")
        effect = "channel_angle"
    size = _size(res, form, p, c)
    summary = (f"The offset follows {name} {what}, up to {size:.3g} µT, "
               f"{size / max(res.floor_ut, 1e-300):.1f}× the recording's floor.")
    ev["size_ut"] = size
    return Located(effect, Kind.PHYSICS, summary, {"channel": name}, p, ev)
