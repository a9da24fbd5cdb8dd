"""Logged channels with lags, gains and nonlinear forms: what the plain channel offset misses.

The catalogue tests each logged channel c (``temp_c``, ``current_a``, a throttle, a servo angle …)
only as an offset proportional to c, with no lag (``diagnose/channels.py``). Here every usable
channel is searched over forms, each judged on the radial residual of the calibration after the
calibration's own linearised refit is projected out:

* ``OFFSET_DELAY`` — an offset vector β·c(t − lag), lag 0 included (lag 0 is the catalogue's term);
* ``OFFSET_FIRST_ORDER`` — β·(c low-passed with time constant τ), the field of a current through
  an inductance or a heat path;
* ``GAIN`` / ``AXIS_GAIN`` — the field scale changes with c: |h| ∝ 1 + g·Δc, so the radial
  residual is F·g·Δc (isotropic) or F·Σ g_k u_k²·Δc (per axis) — told apart from an offset ∝ Δc
  (u·β·Δc) because the two have different columns and the better one wins;
* ``SQUARE`` — β₁Δc + β₂Δc²; ``STEP`` — β·[c > threshold]; ``ANGLE`` — v₁ cos c + v₂ sin c for a
  channel named as an angle (a servo arm), in degrees or in radians, whichever fits.

The search reads the residual with the calibration's own (no-lag) channel terms put back
(``whole``), so a lag, gain or curve is fitted to the channel's whole effect and not to the
misfit a no-lag term fitted first leaves at each switch; a no-lag offset found on a channel the
calibration already carries is its own term again and is not returned (``own_term``); a term
found in its place replaces it (``step.replacing``).

Lags and time constants run on a geometric grid from a quarter of a sample period to a sixth of the span;
an optimum on the grid's upper edge is not reported as a lag. The error rate is controlled over
every channel × form × lag × threshold at once: the largest score (−log₁₀ p) of all candidates is
compared with the largest score of the same search with each channel circularly shifted against
the residual (which keeps the residual's own autocorrelation and slow wander). Only shifts at
which the best candidate's series is nearly uncorrelated with itself are used: a shift that
still lines the channel up with an effect that is there would learn the null from the effect
and raise it (learning the null on the residual with the best term taken out instead removes
the residual's own slow structure too, and under no effect claims it on most recordings). Found
terms are taken out one at a time (at most one per channel) before the next search. A best
candidate that is slow and fails the wander gate (``slow_enough``) sets its channel's slow
candidates aside and the search goes on: on a long recording a current low-passed over minutes
can match the recording's own wander and hide the same current's short lag.

A channel the calibration already carries (the catalogue found its no-lag term) is not asked
again whether it matters: where nothing beats the null, its best lagged offset is still fitted
and kept when a lag fits clearly better than none (``form_of_known``).

Coefficients come with a 95 % interval from the block (HAC) covariance, widened over every lag
within the 95 % profile of the best (the lag's own uncertainty); the lag gets that profile's range.
A found lag's lag, coefficient, profile and interval come from the fit prewhitened by the
residual's own autoregression (``channel_whiten``): a real residual's slow structure, fitted as
if white, pulled the coefficient's direction 20–45 % off on some real recordings. Its form too:
the first-order lag unless a pure delay fits it clearly better (``lag_form``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Mapping

import numpy as np
from numpy.polynomial import legendre

from .. import channels as catalogue
from .. import hygiene
from . import channel_scores as cs
from . import channel_whiten as cw
from .channel_report import describe
from .channel_terms import ANGLE_UNITS, N_LAGS, Form, angle_scale, delayed, lag_grid, low_passed, sample_period_s, term_ut
from ...fit import FitFailure, fit_calibration
from .base import Effect, Kind, Located, Residual

MAX_SAMPLES = 4000  # the search runs on at most this many evenly spaced samples
N_THRESHOLDS = 17  # step thresholds at the 10 … 90 % quantiles of the channel
N_SHIFTS = 39  # circular shifts of each channel for the null
N_SHIFT_GRID = 160  # … chosen among this many evenly spread
N_MIN_SHIFTS = 12
MAX_SHIFT_CORR = 0.3
WANDER_RATIO = catalogue.WANDER_RATIO  # a slow term carries ≥ 4× the slow wander it leaves
SLOW_GATE = 0.5  # … for a series whose slow part carries this share (a pressure, a battery voltage)
N_FINE = 21  # lags of the refined grid about the best coarse lag (± two coarse steps)
CLEAN_RATIO = 2.5  # the best must beat the null learned without it by this factor (see module doc)
ALPHA = 0.002  # family-wise false-claim rate over everything searched
MAX_FOUND = 3
MAX_SLOW_SKIPS = 2  # searches that may set a channel's slow candidates aside (``without_slow``)
ANGLE_WORDS = ("angle", "servo", "deg", "rad", "theta", "phi", "arm", "gimbal", "pan", "rotor")


# -- the forms of one channel -----------------------------------------------------------------
def is_angle(name: str) -> bool:
    return any(w in hygiene.tokens(name) or w in name.lower() for w in ANGLE_WORDS)


def families(name: str, c: np.ndarray, t_s: np.ndarray, rows: np.ndarray) -> list[cs.Family]:
    """Every form tried for channel ``name`` (series on the searched ``rows``)."""
    x = c - c.mean()
    lags = lag_grid(t_s)
    delay = np.column_stack([x] + [delayed(x, t_s, v) for v in lags])[rows]
    first = np.column_stack([low_passed(x, t_s, v) for v in lags])[rows]
    xs = x[rows][:, None]
    q = x[rows] ** 2
    thr = np.quantile(c, np.linspace(0.1, 0.9, N_THRESHOLDS))
    steps = (c[rows][:, None] > thr[None, :]).astype(np.float64)
    steps -= steps.mean(axis=0)
    out = [
        cs.Family(Form.OFFSET_DELAY, name, "offset", delay[:, :, None], np.concatenate([[0.0], lags])),
        cs.Family(Form.OFFSET_FIRST_ORDER, name, "offset", first[:, :, None], lags),
        cs.Family(Form.GAIN, name, "gain", xs[:, :, None], np.zeros(1)),
        cs.Family(Form.AXIS_GAIN, name, "axis_gain", xs[:, :, None], np.zeros(1)),
        cs.Family(Form.SQUARE, name, "offset", np.stack([xs[:, 0], q - q.mean()], axis=1)[:, None, :], np.zeros(1)),
        cs.Family(Form.STEP, name, "offset", steps[:, :, None], thr),
    ]
    if is_angle(name):
        ang = [np.stack([np.cos(c[rows] * angle_scale(k)), np.sin(c[rows] * angle_scale(k))], axis=1) for k in (0, 1)]
        out.append(cs.Family(Form.ANGLE, name, "offset", np.stack(ang, axis=1), np.arange(2.0)))
    return out


def confounded(c: np.ndarray, t_s: np.ndarray) -> bool:
    """A channel that only rises or falls with time cannot be told from a drift
    (``diagnose/channels.py``): it is left to the time term."""
    return abs(float(np.corrcoef(c, t_s)[0, 1])) >= catalogue.CONFOUND_CORR


def candidates(res: Residual) -> dict[str, np.ndarray]:
    """The channels searched: usable, not time, not one that follows the orientation, not one
    that only rises or falls with time."""
    t = np.asarray(res.t_s, np.float64)
    chans = {k: np.asarray(v, np.float64) for k, v in res.channels.items() if k != catalogue.TIME}
    chans = {k: v for k, v in chans.items() if catalogue.usable(v) and not confounded(v, t)}
    if not chans:
        return {}
    kept, left = hygiene.screen(chans, res.u, res.t_s)
    # a servo angle can follow a slow motion by chance: an angle named as such is kept unless its
    # name says it is an attitude angle
    kept.update({lo.channel: chans[lo.channel] for lo in left if not lo.kind and is_angle(lo.channel)})
    return kept


def tried(channels: Mapping[str, np.ndarray], t_s: np.ndarray | None = None) -> list[str]:
    """What was tried for each channel, to be said before "explained by no logged channel"
    (with ``t_s``, a channel that only rises or falls with time is said to be left to drift)."""
    out = []
    for name, c in channels.items():
        c = np.asarray(c, np.float64)
        if name == catalogue.TIME:
            continue
        if not catalogue.usable(c):
            out.append(f"{name}: not tried (constant or with missing values)")
            continue
        if t_s is not None and confounded(c, np.asarray(t_s, np.float64)):
            out.append(f"{name}: not tried on its own (it only rises or falls with time: a drift, tried as time)")
            continue
        forms = (
            f"an offset delayed by 0 or {N_LAGS} lags up to a sixth of the span, the same through a first-order "
            f"lag of {N_LAGS} time constants, a gain (isotropic and per axis), a square term and a step at "
            f"{N_THRESHOLDS} thresholds"
        )
        if is_angle(name):
            forms += ", and the cosine and sine of it as an angle in degrees and in radians"
        out.append(f"{name}: {forms}")
    return out


# -- the search ------------------------------------------------------------------------------
def best(fr: cs.Frame, fams: list[cs.Family]) -> cs.Pick | None:
    return best_each((fr,), fams)[0]


def best_each(frames: tuple[cs.Frame, ...], fams: list[cs.Family]) -> list[cs.Pick | None]:
    """``best`` on each of ``frames``, which differ only in their residual (``Frame.with_r``):
    each family's design (``cs.design_of``) is made once for all of them."""
    tops: list = [None] * len(frames)
    for fam in fams:
        design = cs.design_of(frames[0], fam)
        for i, fr in enumerate(frames):
            ess, _ = cs.scores(fr, fam, design)
            z = cs.log10_p(fr.f_ratio(ess, cs.n_columns(fam)), cs.n_columns(fam))
            j = int(np.argmax(z))
            if tops[i] is None or z[j] > tops[i].score:
                tops[i] = cs.Pick(fam, j, float(z[j]), ess)
    return tops


NESTED = {Form.SQUARE: Form.OFFSET_DELAY, Form.AXIS_GAIN: Form.GAIN}  # form → the simpler form inside it
NESTED_LOG10_P = 3.0  # the extra columns of a bigger form must be significant at 0.1 %
MIN_CURVE = 0.2  # … and a square's curvature at least this share of its straight part


def simpler(fr: cs.Frame, pick: cs.Pick, fams: list[cs.Family]) -> cs.Pick:
    """The nested simpler form of the same channel (a straight line inside the square, one gain
    inside the per-axis gains) unless the extra columns explain significantly more, judged with
    the residual's own autocorrelation (the block covariance's inflation); for a channel named
    as an angle, the arm (cos, sin) whenever it fits within the profile of the best."""
    same = {f.form: f for f in fams if f.channel == pick.fam.channel}
    _, _, infl = cs.hac_cov(fr, pick.fam, pick.j)
    s2 = fr.s2_after(pick.ess[pick.j], cs.n_columns(pick.fam)) * infl
    if Form.ANGLE in same and pick.fam.form is not Form.ANGLE:
        ess, _ = cs.scores(fr, same[Form.ANGLE])
        j = int(np.argmax(ess))
        if ess[j] >= pick.ess[pick.j] - cs.CHI2_1_95 * s2:
            return cs.Pick(same[Form.ANGLE], j, float(cs.log10_p(fr.f_ratio(ess[j], 6), 6)), ess)
    small_form = NESTED.get(pick.fam.form)
    if small_form is None:
        return pick
    small = same[small_form]
    ess, _ = cs.scores(fr, small)
    extra = (pick.ess[pick.j] - ess[0]) / s2
    if (cs.log10_p(extra, cs.n_columns(pick.fam) - cs.n_columns(small)) >= NESTED_LOG10_P and material(fr, pick)
            and curve_beats_shifts(fr, pick)):
        return pick
    return cs.Pick(small, 0, float(cs.log10_p(fr.f_ratio(ess[0], cs.n_columns(small)), cs.n_columns(small))), ess)


def material(fr: cs.Frame, pick: cs.Pick) -> bool:
    """Whether a square term's curvature is at least MIN_CURVE of its straight part at the
    channel's extremes: a large straight term leaves a small square in the radial residual (its
    second order, |β⊥|²Δc²/2F), which is not a square law of the channel."""
    if pick.fam.form is not Form.SQUARE:
        return True
    _, beta = cs.scores(fr, cs.Family(pick.fam.form, pick.fam.channel, "offset", pick.fam.series[:, [pick.j], :], pick.fam.values[:1]))
    s = pick.fam.series[:, pick.j, :]
    lin = np.linalg.norm(beta[0, :3]) * np.max(np.abs(s[:, 0]))
    curve = np.linalg.norm(beta[0, 3:]) * np.ptp(s[:, 1])
    return bool(curve >= MIN_CURVE * lin)


def curve_beats_shifts(fr: cs.Frame, pick: cs.Pick) -> bool:
    """Whether a square term explains more than its own straight line beside the channel's
    square circularly shifted (shifts_for: each nearly uncorrelated with it): the square of a slow
    channel is another slow curve, and a wander it happens to follow is no square law."""
    if pick.fam.form is not Form.SQUARE:
        return True
    s = pick.fam.series[:, pick.j, :]
    shifts = shifts_for(s[:, 1], 0)
    series = np.stack([np.column_stack([s[:, 0], np.roll(s[:, 1], int(k))]) for k in shifts], axis=1)
    ess, _ = cs.scores(fr, cs.Family(pick.fam.form, pick.fam.channel, pick.fam.basis, series, np.zeros(len(shifts))))
    return bool(pick.ess[pick.j] > np.max(ess))


def refined(fr: cs.Frame, pick: cs.Pick, c: np.ndarray, t_s: np.ndarray) -> cs.Pick:
    """A lag pick's form (``lag_form``), lag and ESS from the prewhitened fit (``channel_whiten``):
    the best lag of the coarse grid, then a continuous search between its neighbours, and a fine family about it
    (± two coarse steps, the optimum in it, no lag first) — unless the pick is at an edge of the
    coarse grid (no lag, or beyond the longest tried)."""
    v, j = pick.fam.values, pick.j
    if pick.fam.form not in (Form.OFFSET_DELAY, Form.OFFSET_FIRST_ORDER) or v[j] <= 0 or j == len(v) - 1:
        return pick
    wf = cw.whiten(fr, fr.r - cs.term(fr, pick.fam, j))
    x = c - c.mean()
    form, lag = lag_form(wf, fr, v[np.flatnonzero(v > 0)[:-1]], x, t_s)  # the coarse grid without its edges
    make = delayed if form is Form.OFFSET_DELAY else low_passed
    step = float(v[-1] / v[-2]) ** 2
    lags = np.concatenate([[0.0], np.unique(np.append(np.geomspace(lag / step, lag * step, N_FINE), lag))])
    series = np.column_stack([x] + [make(x, t_s, lag) for lag in lags[1:]])[fr.rows]
    ess = np.array([wf.ess(series[:, k]) for k in range(len(lags))])
    k = int(np.argmax(ess))
    fam = cs.Family(form, pick.fam.channel, "offset", series[:, :, None], lags)
    return cs.Pick(fam, k, float(cs.log10_p(ess[k] / max(wf.s2_after(ess[k]), 1e-300), 3)), ess, wf)


DELAY_LOG10_P = NESTED_LOG10_P  # a pure delay is stated over the first-order lag only at 0.1 %


def lag_form(wf: cw.Whitened, fr: cs.Frame, lags: np.ndarray, x: np.ndarray, t_s: np.ndarray) -> tuple[Form, float]:
    """(form, lag) of a lagged offset from the whitened fit: the delay and the first-order lag,
    each at its own best lag (``cw.best_lag`` over ``lags``), and the first-order lag unless the
    delay explains more by χ²₁ at ``DELAY_LOG10_P``. A current through an inductance or a heat
    path lags as a first-order filter; a pure delay is a log's own clock, so it must be shown.
    The ordinary fit cannot tell them apart on a real residual (the two differed by 0.9–2.1
    times the inflated variance on true delays and by 1.1–1.2 on a true first-order lag taken
    as a delay: bench/locate_eval.py, bench/locate_channel_forms.py); whitened, true forms are
    20–630 apart, and the short fxos8700 take's first-order lag 3–4, within this level."""
    ess_lag = {}
    for form, make in ((Form.OFFSET_DELAY, delayed), (Form.OFFSET_FIRST_ORDER, low_passed)):
        coarse = np.column_stack([make(x, t_s, v) for v in lags])[fr.rows]
        lag = cw.best_lag(wf, lags, coarse, lambda v, make=make: make(x, t_s, v)[fr.rows])
        ess_lag[form] = (wf.ess(make(x, t_s, lag)[fr.rows]), lag)
    (e_delay, lag_delay), (e_first, lag_first) = ess_lag[Form.OFFSET_DELAY], ess_lag[Form.OFFSET_FIRST_ORDER]
    extra = (e_delay - e_first) / max(wf.s2_after(max(e_delay, e_first)), 1e-300)
    if extra > 0 and cs.log10_p(extra, 1) >= DELAY_LOG10_P:
        return Form.OFFSET_DELAY, lag_delay
    return Form.OFFSET_FIRST_ORDER, lag_first


def slow_share(g: np.ndarray) -> float:
    """The share of a series' variance a degree-6 curve in time carries."""
    g = g - g.mean()
    total = float(g @ g)
    if total <= 0:
        return 0.0
    vand = legendre.legvander(np.linspace(-1.0, 1.0, len(g)), catalogue.SLOW_DEGREE)
    smooth = vand @ np.linalg.lstsq(vand, g, rcond=None)[0]
    return float(smooth @ smooth) / total


def slow_enough(fr: cs.Frame, pick: cs.Pick, clean: cs.Frame) -> bool:
    """False when the pick's series is slow (a smooth curve in time carries at least SLOW_GATE
    of it) and its term carries less than WANDER_RATIO × the slow wander it leaves: one slow
    channel matches real wander by chance."""
    if slow_share(pick.fam.series[:, pick.j, 0]) < SLOW_GATE:
        return True
    term_e, rem_e = cs.slow_energies(fr, fr.r - clean.r)
    return term_e >= WANDER_RATIO * rem_e


def without_slow(fams: list[cs.Family], channel: str) -> list[cs.Family]:
    """``fams`` without the candidates of ``channel`` whose series is slow (``slow_share`` at
    least SLOW_GATE): a slow candidate that matched the recording's own wander is set aside, and
    the channel's fast forms (a short lag of a switching current) are searched on."""
    out = []
    for f in fams:
        if f.channel == channel:
            fast = np.array([slow_share(f.series[:, j, 0]) < SLOW_GATE for j in range(f.series.shape[1])], bool)
            f = cs.Family(f.form, f.channel, f.basis, f.series[:, fast], f.values[fast]) if fast.any() else None
        if f is not None:
            out.append(f)
    return out


def shifts_for(g: np.ndarray, max_lag: int) -> np.ndarray:
    """Circular shifts for the null, evenly spread among those at which the picked candidate's
    series ``g`` — shifted, then delayed by any lag the search tries (up to ``max_lag`` samples)
    — is nearly uncorrelated with itself (|ρ| ≤ MAX_SHIFT_CORR), so that an effect that is there
    cannot line up with its own null; the N_MIN_SHIFTS least correlated when too few are."""
    n = len(g)
    gc = g - g.mean()
    acf = np.fft.irfft(np.abs(np.fft.rfft(gc)) ** 2, n) / max(float(gc @ gc), 1e-300)
    grid = np.unique(np.linspace(0, n - 1, N_SHIFT_GRID).astype(int))
    win = np.arange(-2, max_lag + 3)
    rho = np.array([np.max(np.abs(acf[(k + win) % n])) for k in grid])
    keep = grid[rho <= MAX_SHIFT_CORR]
    if len(keep) < N_MIN_SHIFTS:
        keep = np.sort(grid[np.argsort(rho)[:N_MIN_SHIFTS]])
    return keep[np.unique(np.linspace(0, len(keep) - 1, min(len(keep), N_SHIFTS)).astype(int))]


def max_lag_rows(fr: cs.Frame, t_s: np.ndarray) -> int:
    """The longest lag tried, in searched samples."""
    return int(np.ceil(lag_grid(t_s)[-1] / sample_period_s(fr.t_s)))


def null_maxima(frames: tuple[cs.Frame, ...], fams: list[cs.Family], shifts: np.ndarray) -> list[np.ndarray]:
    """For each of ``frames`` (differing only in their residual), the largest score of the whole
    search with every channel circularly shifted by each shift, against the same residual (its
    own autocorrelation and slow wander kept)."""
    if any(f.q is not frames[0].q or f.bases is not frames[0].bases for f in frames):
        raise ValueError("null_maxima's frames must differ only in their residual (Frame.with_r)")
    picks = [best_each(frames, [f.rolled(int(k)) for f in fams]) for k in shifts]
    return [np.array([p[i].score for p in picks]) for i in range(len(frames))]


def whole(res: Residual) -> Residual:
    """``res`` with the calibration's own channel terms put back (its offset moved to where the
    terms sit on average): the search sees each channel's whole effect, so a lag or a gain is
    fitted to all of it rather than to what a no-lag term fitted first left behind."""
    cal = res.calibration
    if not cal.coef_ut_per_unit:
        return res
    shift = cal.channel_offset_ut(res.channels, len(res)).mean(axis=0)
    bare = replace(cal, offset_ut=cal.offset_ut + shift, coef_ut_per_unit={}, reference={})
    return replace(res, calibration=bare)


def own_term(x: Located, cal) -> bool:
    """Whether ``x`` is the calibration's own term found again: a no-lag offset on a channel
    the calibration already carries (nothing to add beside it)."""
    p = x.params
    return bool(p.get("channel") in cal.coef_ut_per_unit and x.effect != LAGGED
                and Form(p["form"]) in (Form.OFFSET_DELAY, Form.OFFSET_FIRST_ORDER))


def search(res: Residual) -> tuple[Located, ...]:
    """Channel terms in the residual of ``res``'s calibration with its own channel terms put back
    (``whole``), each with its form, lag and coefficient interval; a term that is the
    calibration's own again (``own_term``) is not returned."""
    found = _search(whole(res), frozenset(res.calibration.coef_ut_per_unit or {}))
    return tuple(x for x in found if not own_term(x, res.calibration))


def form_of_known(fr: cs.Frame, fams: list[cs.Family], known: frozenset) -> cs.Pick | None:
    """The best lagged offset (delay or first-order, a lag inside the grid: neither none nor the
    longest tried, which is no stated lag) on a channel the calibration already carries, or None.
    That the channel moves the offset is the catalogue's finding, already tested; what is left to
    ask is its form, which the lag's own profile answers
    (``channel_report``: a lag is stated only where no lag fits clearly worse). The circular-shift
    null asks the first question again and cannot answer it for a periodic channel (a current
    switched every 9 s on a 56 s recording): every shift, delayed by a lag tried, lines up with
    the effect again, and the null is learned from it."""
    lags = [f for f in fams if f.channel in known and f.form in (Form.OFFSET_DELAY, Form.OFFSET_FIRST_ORDER)]
    pick = best(fr, lags) if lags else None
    inside = pick is not None and 0 < pick.fam.values[pick.j] < pick.fam.values[-1]
    return pick if inside else None


def _search(res: Residual, known: frozenset = frozenset()) -> tuple[Located, ...]:
    chans = candidates(res)
    if not chans or len(res) < 200:
        return ()
    t = np.asarray(res.t_s, np.float64)
    rows = np.unique(np.linspace(0, len(t) - 1, min(len(t), MAX_SAMPLES)).astype(int))
    cal = res.calibration
    fr = cs.frame(res.r_ut, res.u, np.asarray(cal.soft_iron), cal.field_ut, rows, t)
    fams = [f for name, c in chans.items() for f in families(name, c, t, rows)]
    found = []
    for _ in range(MAX_FOUND + MAX_SLOW_SKIPS):
        pick = best(fr, fams)
        if pick is None or len(found) == MAX_FOUND:
            break
        score = pick.score
        clean = fr.with_r(fr.r - cs.term(fr, pick.fam, pick.j))
        shifts = shifts_for(pick.fam.series[:, pick.j, 0], max_lag_rows(fr, t))
        null_raw, null_clean = null_maxima((fr, clean), fams, shifts)
        threshold = min(cs.gumbel_threshold(null_raw, ALPHA), CLEAN_RATIO * cs.gumbel_threshold(null_clean, ALPHA))
        if score <= threshold:
            pick = form_of_known(fr, fams, known)
            if pick is None:
                break
        pick = refined(fr, simpler(fr, pick, fams), chans[pick.fam.channel], t)
        clean = fr.with_r(fr.r - cs.term(fr, pick.fam, pick.j))
        if not slow_enough(fr, pick, clean):
            fams = without_slow(fams, pick.fam.channel)  # its fast forms may still be there
            continue
        null = null_raw
        evidence = {"score": score, "threshold": threshold, "null_max": float(np.max(null)), "n_shifts": len(null),
                    "form_of_catalogue_term": bool(score <= threshold)}
        located, fr = relinearized(res, fr, pick, fams, evidence)
        found.append(located)
        fams = [f for f in fams if f.channel != pick.fam.channel]
        if not fams:
            break
    return tuple(found)


def relinearized(res: Residual, fr: cs.Frame, pick: cs.Pick, fams: list[cs.Family], evidence: dict):
    """(the found term, the frame left for the next search), both about the calibration the term
    leaves: the calibration refitted on the samples with the term taken out, and the original
    samples' residual under it searched again over the same channel's forms. The first fit is
    linearised about a calibration the term itself distorted, which biases a large term's
    coefficient by more than its interval and leaves a misfit another channel could collect."""
    c = np.asarray(res.channels[pick.fam.channel], np.float64)
    first = describe(res, fr, pick, c, evidence)
    cal = res.calibration
    model = "sphere" if np.allclose(cal.soft_iron, np.eye(3)) else "ellipsoid"
    fit = fit_calibration(remove(res.m_ut, res.t_s, res.channels, first), model=model, outliers=False, reasons=False)
    if isinstance(fit, FitFailure):
        return first, fr.with_r(fr.r - cs.term(fr, pick.fam, pick.j))
    cal2 = fit.calibration
    res2 = replace(res, calibration=cal2)
    fr2 = cs.frame(res2.r_ut, res2.u, np.asarray(cal2.soft_iron), cal2.field_ut, fr.rows, np.asarray(res.t_s, np.float64))
    same = [f for f in fams if f.channel == pick.fam.channel]
    again = best(fr2, same)
    again = refined(fr2, simpler(fr2, again, same), c, np.asarray(res.t_s, np.float64))
    found = describe(res2, fr2, replace(again, score=pick.score), c, evidence)
    return found, fr2.with_r(fr2.r - cs.term(fr2, again.fam, again.j))


def remove(m_ut: np.ndarray, t_s: np.ndarray, channels: Mapping[str, np.ndarray], located: Located) -> np.ndarray:
    """The samples with the located channel term taken out about the channel's reference value.

    An offset term (any lag, square, step, angle) is subtracted as f(c) − f(reference); a gain is
    divided out about the reference, around the calibration's offset. The calibration refitted
    on what is returned is the one in force when the channel sits at its reference value: no
    current (``current_a`` at 0 A) for a current, and the channel's value at the end of the
    recording for every other channel (the calibration in force at the end)."""
    m = np.asarray(m_ut, np.float64).reshape(-1, 3)
    p = located.params
    name = p["channel"]
    if name not in channels:
        raise ValueError(f"remove: channel {name!r} of the located term is not among the channels given")
    c = np.asarray(channels[name], np.float64)
    if len(c) != len(m) or len(np.asarray(t_s)) != len(m):
        raise ValueError(f"remove: {len(m)} samples, {len(c)} channel values and {len(t_s)} times differ")
    form = Form(p["form"])
    if form in (Form.GAIN, Form.AXIS_GAIN):
        b = np.asarray(p["center_ut"], np.float64)
        g = np.asarray(p["gain_per_unit"], np.float64).reshape(-1)
        scale = 1.0 + np.outer(c - p["reference"], g * np.ones(3))
        return b + (m - b) / scale
    return m - term_ut(form, p, c, np.asarray(t_s, np.float64))


def _searched_above(res: Residual) -> tuple[Located, ...]:
    """Rows after the first only name an effect the first row's search returns."""
    return ()


# every effect name the search can return, each with its model; the search runs once (first row)
LAGGED = "lagged_channel"
NAMES = (LAGGED, "temperature_drift", "current_interference", "channel_offset", "temperature_gain",
         "channel_gain", "channel_square", "channel_step", "channel_angle")
EFFECTS = tuple(Effect(n, Kind.PHYSICS, search if i == 0 else _searched_above, remove) for i, n in enumerate(NAMES))
EFFECT = EFFECTS[0]
