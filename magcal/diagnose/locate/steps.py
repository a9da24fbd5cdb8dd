"""Change points in time: a hard-iron step, a soft-iron change, and stretches where the data misbehave.

- ``hard_iron_step``: something magnetic put down or picked up mid-recording moves the offset
  by δ at τ. After it the radial residual is ≈ u·(Wδ) (u the direction, W the soft iron)
  relative to the level before. Every candidate τ is judged in a window of ±``half_window_s``
  around it: the offset there may wander as a quadratic in time (a slow wander or a ramp is
  absorbed — it is not a step), and the step must add beyond it. The statistic (the drop in
  residual sum of squares, over the local variance and the recording's own inflation f² of
  direction-weighted sums, ``steps_scan.inflation``) is χ²₃ under no step; the threshold is
  Bonferroni over the span's independent windows at family-wise ``ALPHA``. Found steps are
  taken out one at a time and the scan repeated (up to ``MAX_STEPS``). δ comes with its 1σ and
  τ with the interval of times whose fit is within χ²₁(95 %) of the best.
- ``soft_iron_change``: the shape (gains, soft iron) changes at τ. With the offset free to
  wander (piecewise linear in time) and to step at τ, the 6 shape terms after τ (r moves by
  F·uᵀEu under h → (I + E)h) are tested on a grid of τ (Bonferroni over the grid, the
  same inflation on shape-weighted sums) — tested only along the shape directions both sides'
  coverage determines (each side's information on the shape terms, its own offset linear in
  time fitted, along the directions it pins as ``softiron.determined_directions`` judges them —
  to ``SHAPE_SIGMA_MAX`` and not trading with the offset; the two sides' parallel sum pins a
  direction's change to √2 × ``SHAPE_SIGMA_MAX``): at
  the τ the six-direction scan places, the statistic is χ²_k over those k directions.
  A shape that seems to change only along directions one side leaves free is that side's own
  misfit, not evidence of a change, and nothing is said of it.
- ``unexplained_structure``: a stretch whose residual RMS (after the wander and any found step)
  stands far above the recording's typical window and its floor, explained by no step, and
  steps that undo each other — the honest remainder (magcal.diagnose.locate.steps_rest).

Limits (measured with bench/locate_steps.py): the local test sees a step through the jump of
r at τ, which is u(τ)·(Wδ) — a step across the direction the board points at that moment shows
little jump and is found late or not at all, however large; its vector, once found, comes from
the segments either side, which see every direction. A recording whose own shape drifts
(seen on a real hand-waved recording) is reported as a soft-iron change.

``remove`` for a step shifts the samples before τ by δ, and for a soft-iron change maps the
samples before τ through the calibration fitted on them into the calibration fitted on the
samples after τ: the calibration refitted on the result is the one in force at the END of the
recording, which is what ``write`` puts on the device.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from ...fit import fit_calibration
from ...fit.tails import chi2_isf, chi2_sf
from . import steps_rest as rest_of
from . import steps_scan as scan
from .change_trained import remove_soft_trained, remove_step_trained
from ..softiron import MAX_GAIN_SIGMA, MIN_UNIQUE
from ..timewords import duration, instant
from .base import Effect, Kind, Located, Residual, noise_and_wander_ut

STEP = "hard_iron_step"
SOFT = "soft_iron_change"
ALPHA = 0.01  # family-wise false-claim rate over every time scanned
MAX_STEPS = 3
MAX_CANDIDATES = 300  # candidate times per scan (every half/10 on short recordings); refined to the sample
HALF_SHARE = 1.0 / 15.0  # the local window's half-width as a share of the span …
HALF_RANGE_S = (3.0, 15.0)  # … within these bounds
MIN_SIDE = 10  # samples each side of τ within its window (the window holds at least 4× this each side)
INTERVAL_CHI2 = float(chi2_isf(0.05, 1))
CHI2_3_MEDIAN = float(chi2_isf(0.5, 3))
CHI2_6_MEDIAN = float(chi2_isf(0.5, 6))
STEP_MIN_OVER_FLOOR = 1.0  # a step or shape change smaller than the floor is not claimed
SOFT_GRID = 40  # soft-iron candidate times over the middle of the span
SOFT_EDGE = 0.1  # … leaving this share of the span at each end
SOFT_KNOT_SHARE = 0.25  # the offset may wander piecewise-linearly with knots this share of the span apart
STEP_OR_SHAPE_ALPHA = 0.05  # level of the two nested tests that tell a found step from a change of shape at its time
SOFT_MAX_N = 3000  # samples the soft-iron scan uses (evenly thinned)
SHAPE_SIGMA_MAX = MAX_GAIN_SIGMA  # 1σ of a shape direction (relative gain) a side's coverage must reach


@dataclass(frozen=True)
class HardIronStep:
    """One hard-iron step found: its time, interval, change of the local offset (h frame) and its
    covariance, the level before it, and the statistic against its threshold."""

    tau_s: float
    interval_s: tuple[float, float]
    d_h: np.ndarray
    cov_h: np.ndarray
    level_h: np.ndarray
    stat: float
    threshold: float


def half_window_s(t_s: np.ndarray, clock: bool = True) -> float:
    """The local window's half-width for this recording's span; without a clock (t_s the sample
    index) bounds in seconds mean nothing, and the share of the span alone sets it."""
    span = float(t_s[-1] - t_s[0])
    dt = float(np.median(np.diff(t_s)))
    share = np.clip(span * HALF_SHARE, *HALF_RANGE_S) if clock else span * HALF_SHARE
    return float(max(share, 4 * MIN_SIDE * dt))


def _check(res: Residual) -> None:
    t = np.asarray(res.t_s, float)
    if len(t) != len(res.m_ut) or len(t) < 2 or not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise ValueError("t_s must hold one finite, non-decreasing time per sample")


# -- hard-iron steps ----------------------------------------------------------------------


def _best(u, t, r, half, f2) -> tuple[float, float, float]:
    """(largest statistic, its time, the median statistic) over the candidate grid; a
    candidate needs ``MIN_SIDE`` samples each side of it within its window. Every candidate's
    local regression comes from one pass of prefix sums (``steps_scan.Moments``)."""
    per_half = max(1, int(min(10, MAX_CANDIDATES * half / max(float(t[-1] - t[0]), half))))
    taus = scan.candidates(t, half, per_half)
    lo, k, hi = (np.searchsorted(t, taus - half, "left"), np.searchsorted(t, taus, "left"),
                 np.searchsorted(t, taus + half, "right"))
    ok = (k - lo >= MIN_SIDE) & (hi - k >= MIN_SIDE)
    if not np.any(ok):
        return 0.0, float("nan"), 0.0
    rss0, rss1 = scan.Moments(u, t, r, half).rss(lo[ok], k[ok], hi[ok], taus[ok])
    var = rss1 / np.maximum(hi[ok] - lo[ok] - 12, 1)
    stats = (rss0 - rss1) / np.maximum(var * f2, 1e-300)
    j = int(np.argmax(stats))
    return float(stats[j]), float(taus[ok][j]), float(np.median(stats))


def _refine(u, t, r, half, tau0, f2, threshold) -> HardIronStep:
    """The best sample time near ``tau0`` (window fixed at tau0), its interval and the step."""
    w = scan.window(t, tau0, half)
    uw, tw, rw = u[w], t[w], r[w]
    near = tw[np.abs(tw - tau0) <= half / 5.0]
    taus = np.unique(np.concatenate([near, [tau0]]))
    k = np.searchsorted(tw, taus, "left")
    keep = (k >= 1) & (k < len(tw))
    taus, k = taus[keep], k[keep]
    ends = np.zeros(len(k), np.int64)
    rss0, rss = scan.Moments(uw, tw, rw, half).rss(ends, k, ends + len(tw), np.full(len(k), tau0))
    j = int(np.argmin(rss))
    tau = float(taus[j])
    f1 = scan.step_gain(uw, tw, rw, tau, half)[1]
    var = f1.rss / max(f1.n - f1.p, 1) * f2
    inside = taus[rss <= rss[j] + INTERVAL_CHI2 * var]
    dt = float(np.median(np.diff(tw))) if len(tw) > 1 else 0.0  # the time is known to a sample at best
    inside = np.concatenate([inside, [tau - dt, tau + dt]])
    stat = float(rss0[j] - f1.rss) / var
    return HardIronStep(tau, (float(inside.min()), float(inside.max())), f1.coef[-3:], var * f1.xtx_inv[-3:, -3:], f1.coef[:3],
                stat, threshold)


def measure(u, t, r, q, f2, steps: list[HardIronStep]) -> list[HardIronStep]:
    """Each step's vector from the segments between the steps: a constant offset per segment
    (3 columns each) with the calibration's shape misfit (Q) shared — the jump alone fixes only
    the step's part along the direction at τ; the segments see every direction."""
    cuts = [s.tau_s for s in steps]
    seg = np.searchsorted(cuts, t, "right")
    x = np.hstack([q] + [u * (seg == k)[:, None] for k in range(len(steps) + 1)])
    f = scan.lsq(x, r)
    var = f.rss / max(f.n - f.p, 1) * f2
    out = []
    for k, s in enumerate(steps):
        a, b = 6 + 3 * k, 6 + 3 * (k + 1)
        d = f.coef[b : b + 3] - f.coef[a : a + 3]
        c = f.xtx_inv
        cov = var * (c[a : a + 3, a : a + 3] + c[b : b + 3, b : b + 3] - c[a : a + 3, b : b + 3] - c[b : b + 3, a : a + 3])
        out.append(HardIronStep(s.tau_s, s.interval_s, d, cov, f.coef[a : a + 3], s.stat, s.threshold))
    return out


def find_steps(u, t, r, half, f2) -> tuple[list[HardIronStep], np.ndarray]:
    """The steps found (time order) and the residual with them taken out."""
    span = float(t[-1] - t[0])
    threshold = float(chi2_isf(ALPHA / max(1.0, span / half), 3))
    steps: list[HardIronStep] = []
    r = r.copy()
    for i in range(MAX_STEPS):
        stat, tau, typical = _best(u, t, r, half, f2)
        if i == 0 and typical > CHI2_3_MEDIAN:  # the scan's own typical value says the residual is rougher
            stat, f2 = stat * CHI2_3_MEDIAN / typical, f2 * typical / CHI2_3_MEDIAN
        if not stat >= threshold:
            break
        s = _refine(u, t, r, half, tau, f2, threshold)
        steps.append(s)
        r = r - (u @ s.d_h) * (t >= s.tau_s)
    return sorted(steps, key=lambda s: s.tau_s), r


def _step_located(s: HardIronStep, cal, floor_ut: float) -> Located:
    w_inv = np.linalg.inv(cal.soft_iron)
    d = w_inv @ s.d_h
    cov = w_inv @ s.cov_h @ w_inv.T
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    before = cal.offset_ut + w_inv @ s.level_h
    size = float(np.linalg.norm(d))
    half = max(s.tau_s - s.interval_s[0], s.interval_s[1] - s.tau_s)
    over = size / floor_ut if floor_ut > 0 else float("inf")
    summary = (f"a hard-iron step of ({d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f}) µT at {instant(s.tau_s)} (±{duration(half, '.2f')}), "
               f"{over:.1f}× the recording's floor")
    return Located(STEP, Kind.PHYSICS, summary, {"time_s": [s.tau_s], "direction": (d / size).tolist()},
                   {"step_ut": d, "step_sigma_ut": sigma, "offset_before_ut": before, "offset_after_ut": before + d,
                    "time_s": s.tau_s, "time_interval_s": list(s.interval_s)},
                   {"size_ut": size, "size_over_floor": over, "statistic": s.stat, "threshold": s.threshold,
                    "alpha": ALPHA})


def remove_step(m_ut, t_s, channels, located: Located) -> np.ndarray:
    """The samples before the step shifted by it: the offset after the step in force throughout,
    so a calibration refitted on them is the one in force at the end of the recording."""
    m = np.array(m_ut, dtype=np.float64, copy=True)
    before = np.asarray(t_s, float) < float(located.params["time_s"])
    m[before] += np.asarray(located.params["step_ut"], float)
    return m


# -- soft-iron change ---------------------------------------------------------------------


@dataclass(frozen=True)
class ShapeChange:
    """The best soft-iron change time, its interval over the grid, the change E of the shape
    terms (xx, yy, zz, xy, xz, yz) with 1σ — tested, and nonzero, only along ``directions``
    (6, k): the shape directions both sides' coverage determines — and the statistic (χ²_k)."""

    tau_s: float
    interval_s: tuple[float, float]
    e: np.ndarray
    sigma: np.ndarray
    stat: float
    threshold: float
    directions: np.ndarray
    typical: float = 0.0  # the median statistic over the grid
    explained_ut: float = float("inf")  # RMS per sample after τ of what the change adds to the step-only fit
    allowed_ut: float = 0.0  # the noise and slow offset wander of the residual with that taken out, together

    @property
    def tested(self) -> int:
        """How many of the 6 shape directions the change was tested in."""
        return int(self.directions.shape[1])


@dataclass(frozen=True)
class _Grid:
    """Per candidate τ: the RSS with an offset step at τ (``rss0``) and with the shape changing
    too in all 6 directions (``rss_full``, its coefficients), and the latter's normal equations."""

    taus: np.ndarray
    rss0: np.ndarray
    rss_full: np.ndarray
    coef_full: list
    normal: list
    rtr: float


def _thin(n: int) -> np.ndarray:
    return np.arange(0, n, max(1, int(np.ceil(n / SOFT_MAX_N))))


def _shape_scan(base, u, q, t, r, taus) -> _Grid:
    """The grid's fits from tail Gram matrices, one pass over the samples (``_Grid``)."""
    z = np.hstack([base, u, q])
    nb = base.shape[1]
    full, fcross = z.T @ z, z.T @ r
    rtr = float(r @ r)
    grams, cross = scan.tail_grams(z, r, np.searchsorted(t, taus, "left"))
    rss0, rss1, coefs, normal = [], [], [], []
    for g, c in zip(grams, cross):
        xtx = np.block([[full[:nb, :nb], g[:nb, nb:]], [g[nb:, :nb], g[nb:, nb:]]])
        xtr = np.concatenate([fcross[:nb], c[nb:]])
        rss0.append(scan.solve_rss(xtx[: nb + 3, : nb + 3], xtr[: nb + 3], rtr)[0])
        rss, coef, _ = scan.solve_rss(xtx, xtr, rtr)
        rss1.append(rss)
        coefs.append(coef)
        normal.append((xtx, xtr))
    return _Grid(np.asarray(taus, float), np.array(rss0), np.array(rss1), coefs, normal, rtr)


def _tested_at(grid: _Grid, j: int, u, q, t, nb: int, f2: float) -> tuple:
    """The change at the grid's τ number ``j`` fitted only along the shape directions both
    sides determine (each side's information on the shape terms, with its own offset linear in
    time fitted): (RSS, variance, base and offset-step coefficients, E, E's covariance, the
    directions (6, k)). A change along a direction one side leaves free is no evidence."""
    after = t >= grid.taus[j]
    s = ((t - t[0]) / max(float(np.ptp(t)), 1e-9))[:, None]
    w = np.hstack([u, u * s, q])
    n, m = len(t), nb + 3
    var = grid.rss_full[j] / max(n - m - 6, 1) * f2
    info = [scan.shape_information(w[side].T @ w[side], 6, var, SHAPE_SIGMA_MAX, MIN_UNIQUE) for side in (~after, after)]
    d = scan.shared_directions(*info, SHAPE_SIGMA_MAX)
    tm = np.zeros((m + 6, m + d.shape[1]))
    tm[:m, :m] = np.eye(m)
    tm[m:, m:] = d
    xtx, xtr = grid.normal[j]
    rss, coef, inv = scan.solve_rss(tm.T @ xtx @ tm, tm.T @ xtr, grid.rtr)
    var = rss / max(n - m - d.shape[1], 1) * f2
    return rss, var, coef[:m], d @ coef[m:], var * d @ inv[m:, m:] @ d.T, d


def _soft_base(u, t, r, field_ut: float, step_times) -> tuple:
    """The soft-iron scans' samples (thinned) and the columns all their fits hold (the offset's
    piecewise-linear wander, the calibration's shape misfit Q, the steps)."""
    k = _thin(len(t))
    u, t, r = u[k], t[k], r[k]
    q = scan.quad(u, field_ut)
    steps = [u * (t >= x)[:, None] for x in step_times]
    return u, t, r, q, np.hstack([scan.wander_columns(u, t, float(t[-1] - t[0]) * SOFT_KNOT_SHARE), q] + steps)


def shape_change(u, t, r, field_ut: float, half: float, step_times=()) -> ShapeChange | None:
    """The soft-iron change scan (module docstring), with the offset stepping at ``step_times``
    too: τ placed by the change in all six shape directions, the change then tested only along
    those both sides determine. None when the span is too short to scan or no shape direction
    is determined on both sides of τ."""
    u, t, r, q, base = _soft_base(u, t, r, field_ut, step_times)
    span = float(t[-1] - t[0])
    nb = base.shape[1]
    taus = t[0] + span * np.linspace(SOFT_EDGE, 1 - SOFT_EDGE, SOFT_GRID)
    taus = taus[[min(np.sum(t < x), np.sum(t >= x)) >= 6 * MIN_SIDE for x in taus]]
    if len(taus) < 3:
        return None
    grid = _shape_scan(base, u, q, t, r, taus)
    null = float(np.min(grid.rss0))  # the null: the best single offset step on the grid, wherever it is
    i = int(np.argmax(null - grid.rss_full))
    after = (t >= taus[i])[:, None]
    e1 = r - np.hstack([base, u * after, q * after]) @ grid.coef_full[i]
    f2 = scan.inflation(e1, q / field_ut, max(1, int(np.sum(t - t[0] < half))))
    var = grid.rss_full / max(len(t) - nb - 9, 1) * f2
    typical = float(np.median((grid.rss0 - grid.rss_full) / var))  # the grid's own typical value of the χ²₆ statistic
    inside = taus[grid.rss_full <= grid.rss_full[i] + INTERVAL_CHI2 * var[i]]
    width = taus[1] - taus[0]
    fine = _shape_scan(base, u, q, t, r, np.linspace(taus[i] - width, taus[i] + width, 21))
    null = min(null, float(np.min(fine.rss0)))
    j = int(np.argmax(null - fine.rss_full))
    rss, var_j, coef, e, cov, d = _tested_at(fine, j, u, q, t, nb, f2)
    if d.shape[1] == 0:
        return None
    tau = float(fine.taus[j])
    threshold = float(chi2_isf(ALPHA / len(taus), d.shape[1]))
    inside = np.concatenate([inside, [tau]])
    explained, allowed = _net(base, u, q, t, r, tau, coef, e)
    return ShapeChange(tau, (float(inside.min()), float(inside.max())), e, np.sqrt(np.clip(np.diag(cov), 0.0, None)),
                       float((null - rss) / var_j), threshold, d, typical, explained, allowed)


class Told(Enum):
    """What the two nested tests at a change's time (``told_at``) say the change is."""
    STEP = "the offset stepped: a change of shape there adds nothing beyond the step"
    SHAPE = "the shape changed: an offset step there adds nothing beyond the change of shape"
    MOSTLY_STEP = "each adds beyond the other, the step's addition the less likely by chance"
    MOSTLY_SHAPE = "each adds beyond the other, the shape's addition the less likely by chance"
    EITHER = "neither adds beyond the other: the data cannot tell which"


def told_at(u, t, r, field_ut: float, half: float, step: HardIronStep, step_times=()) -> tuple[Told, ShapeChange | None]:
    """A found step told by two nested tests at its time τ at ``STEP_OR_SHAPE_ALPHA`` (the offset
    wandering and stepping at the other ``step_times``): does the shape change, along the
    directions both sides determine, add to an offset step at τ beyond chance (χ²_k), and does
    the step add to the shape change (χ²₃)? A gain change seen through a local offset model looks
    like a step (and a step, under a motion that ties direction to time, like a gain change). Where
    no shape direction is determined on both sides (or a side is short) it is told a step; where
    each adds, the addition less likely by chance says which it mostly is. With the shape adding,
    the change of shape at τ."""
    u, t, r, q, base = _soft_base(u, t, r, field_ut, step_times)
    tau = step.tau_s
    if min(np.sum(t < tau), np.sum(t >= tau)) < 6 * MIN_SIDE:
        return Told.STEP, None
    grid = _shape_scan(base, u, q, t, r, np.array([tau]))
    after = (t >= tau)[:, None]
    e1 = r - np.hstack([base, u * after, q * after]) @ grid.coef_full[0]
    f2 = scan.inflation(e1, q / field_ut, max(1, int(np.sum(t - t[0] < half))))
    rss, var, coef, e, cov, d = _tested_at(grid, 0, u, q, t, base.shape[1], f2)
    if d.shape[1] == 0:
        return Told.STEP, None
    over_step = float(grid.rss0[0] - rss) / var
    step_over_shape = float(scan.lsq(np.hstack([base, (q * after) @ d]), r).rss - rss) / var
    threshold = float(chi2_isf(STEP_OR_SHAPE_ALPHA, d.shape[1]))
    shape_adds, step_adds = over_step >= threshold, step_over_shape >= chi2_isf(STEP_OR_SHAPE_ALPHA, 3)
    if not shape_adds:
        return (Told.STEP if step_adds else Told.EITHER), None
    told = Told.SHAPE
    if step_adds:
        told = Told.MOSTLY_SHAPE if chi2_sf(over_step, d.shape[1]) < chi2_sf(step_over_shape, 3) else Told.MOSTLY_STEP
    explained, allowed = _net(base, u, q, t, r, tau, coef, e)
    return told, ShapeChange(tau, step.interval_s, e, np.sqrt(np.clip(np.diag(cov), 0.0, None)), over_step, threshold, d,
                                   0.0, explained, allowed)


def _net(base, u, q, t, r, tau: float, coef: np.ndarray, e: np.ndarray) -> tuple[float, float]:
    """(what a shape change ``e`` at τ adds to the fit with an offset step at τ alone, as an RMS
    per sample after τ; the noise and slow offset wander of ``r`` with that part taken out,
    together, ``base.noise_and_wander_ut``) — the change sized against the recording measured
    without it. ``coef``: the base and offset-step coefficients fitted with the change."""
    after = (t >= tau)[:, None]
    x0 = np.hstack([base, u * after])
    net = x0 @ coef + (q * after) @ e - x0 @ scan.lsq(x0, r).coef
    explained = float(np.sqrt(np.sum(net**2) / max(int(after.sum()), 1)))
    return explained, float(np.hypot(*noise_and_wander_ut(r - net, u)))


def _soft_located(c: ShapeChange, floor_ut: float, field_ut: float) -> Located:
    """The change as a named effect, tested only along the shape directions both sides' coverage
    determines (``ShapeChange.directions``): a change along a direction one side leaves free
    cannot be told from that side's own misfit, so it is neither claimed nor left as the
    remainder; the summary says how many of the six directions were tested."""
    gains = c.e[:3]
    size_ut = float(np.max(np.abs(c.e)) * field_ut)
    half = max(c.tau_s - c.interval_s[0], c.interval_s[1] - c.tau_s)
    where = {"time_s": [c.tau_s], "axis": ["x", "y", "z"][int(np.argmax(np.abs(gains)))]}
    evidence = {"size_ut": size_ut, "size_over_floor": size_ut / floor_ut if floor_ut > 0 else float("inf"),
                "statistic": c.stat, "threshold": c.threshold, "alpha": ALPHA, "explained_ut": c.explained_ut,
                "noise_and_wander_without_ut": c.allowed_ut, "shape_directions_tested": c.tested}
    params = {"time_s": c.tau_s, "time_interval_s": list(c.interval_s), "gain_change": gains,
              "gain_change_sigma": c.sigma[:3], "shape_change": c.e, "shape_change_sigma": c.sigma,
              "tested_directions": c.directions.T}
    g = ", ".join(f"{100 * x:+.1f} %" for x in gains)
    summary = f"the soft iron changed at {instant(c.tau_s)} (±{duration(half)}): gains x, y, z by {g}"
    if c.tested < 6:
        summary += (f" (tested in the {c.tested} of 6 shape directions the coverage on both sides determines; "
                    "a change in the others cannot be told)")
    return Located(SOFT, Kind.PHYSICS, summary, where, params, evidence)


def remove_soft(m_ut, t_s, channels, located: Located) -> np.ndarray:
    """The samples before τ mapped through their own calibration into the one fitted on the
    samples after τ alone (full ellipsoid): a calibration refitted on the result is the one in
    force at the end of the recording. Unchanged where either side cannot be fitted."""
    m = np.asarray(m_ut, dtype=np.float64)
    before = np.asarray(t_s, float) < float(located.params["time_s"])
    fb = fit_calibration(m[before], model="ellipsoid", reasons=False)
    fa = fit_calibration(m[~before], model="ellipsoid", reasons=False)
    if not fb or not fa:
        return m.copy()
    cb, ca = fb.calibration, fa.calibration
    h = cb.correct(m[before]) * (ca.field_ut / cb.field_ut)
    out = m.copy()
    out[before] = ca.distort(h)
    return out


def remove_offset_change(m_ut, t_s, channels, located: Located) -> np.ndarray:
    """The simpler account of a soft-iron change, the one its scan tested it against: only the
    offset changes at τ (each side's own fitted offset), the shape stays as it is. Unchanged
    where either side cannot be fitted."""
    m = np.asarray(m_ut, dtype=np.float64)
    before = np.asarray(t_s, float) < float(located.params["time_s"])
    fb = fit_calibration(m[before], model="ellipsoid", reasons=False)
    fa = fit_calibration(m[~before], model="ellipsoid", reasons=False)
    out = m.copy()
    if fb and fa:
        out[before] += fa.calibration.offset_ut - fb.calibration.offset_ut
    return out


# -- the search -----------------------------------------------------------------------------


def _shape_corrected(u, t, r, shape_cols: np.ndarray, half, steps: list[HardIronStep]) -> np.ndarray:
    """r with the calibration's shape misfit (``shape_cols``: Q, and Q after a soft-iron change)
    taken out, fitted with the wander and the steps found so far, so a local offset search
    does not chase it."""
    cols = [shape_cols, scan.wander_columns(u, t, half)] + [u * (t >= s.tau_s)[:, None] for s in steps]
    coef = scan.lsq(np.hstack(cols), r).coef
    return r - shape_cols @ coef[: shape_cols.shape[1]]


def _all_steps(u, t, r, shape_cols, half, f2) -> tuple[list[HardIronStep], np.ndarray]:
    steps, rest = find_steps(u, t, _shape_corrected(u, t, r, shape_cols, half, []), half, f2)
    if steps:
        steps, rest = find_steps(u, t, _shape_corrected(u, t, r, shape_cols, half, steps), half, f2)
    return steps, rest


def _big(c: ShapeChange, field_ut: float, floor_ut: float) -> bool:
    return float(np.max(np.abs(c.e)) * field_ut) >= STEP_MIN_OVER_FLOOR * floor_ut


def _soft_change(u, t, r, field_ut, floor_ut, half, steps: list[HardIronStep]) -> ShapeChange | None:
    """A soft-iron change, claimed where the shape changes beyond chance with the offset steps
    found allowed for (a step is not a change of shape). Placed by the scan without those
    steps where it agrees to a window (a change of shape seen through a local offset model can
    look like steps, and such false steps must not pull its time)."""
    with_steps = shape_change(u, t, r, field_ut, half, [s.tau_s for s in steps])
    if with_steps is None or with_steps.stat < with_steps.threshold or not _big(with_steps, field_ut, floor_ut):
        return None
    alone = shape_change(u, t, r, field_ut, half) if steps else None
    if alone is not None and alone.stat >= alone.threshold and abs(alone.tau_s - with_steps.tau_s) <= half:
        return alone
    return with_steps


def _told(u, t, r, field_ut, floor_ut, half, steps: list[HardIronStep], shape: ShapeChange | None) -> ShapeChange | None:
    """The soft-iron change once every found step is told (``told_at``): the scan's change is
    dropped where the found step within a window of it is told a step; where the scan found none,
    the strongest found step told (mostly) a change of shape is that change."""
    told = [(s, *told_at(u, t, r, field_ut, half, s, [o.tau_s for o in steps if o is not s]))
            for s in sorted(steps, key=lambda s: -s.stat)]
    if shape is not None:
        near = [k for s, k, _ in told if abs(s.tau_s - shape.tau_s) <= half]
        return None if near and near[0] is Told.STEP else shape
    shaped = (Told.SHAPE, Told.MOSTLY_SHAPE)
    return next((c for _, k, c in told if k in shaped and _big(c, field_ut, floor_ut)), None)


def search(res: Residual) -> tuple[Located, ...]:
    """Every step, soft-iron change and misbehaving stretch in one residual (module docstring)."""
    _check(res)
    t = np.asarray(res.t_s, float)
    u, r = res.u, res.r_ut
    if float(t[-1] - t[0]) < 4 * HALF_RANGE_S[0]:
        return ()
    half = half_window_s(t, res.clock)
    cal, floor = res.calibration, float(res.floor_ut)
    q = scan.quad(u, cal.field_ut)
    x = np.hstack([scan.wander_columns(u, t, half), q])
    f2 = scan.inflation(r - x @ scan.lsq(x, r).coef, u, max(1, int(np.sum(t - t[0] < half))))
    steps, rest = _all_steps(u, t, r, q, half, f2)
    shape = _soft_change(u, t, r, cal.field_ut, floor, half, steps)
    shape = _told(u, t, r, cal.field_ut, floor, half, steps, shape) if steps else shape
    found: list[Located] = []
    if shape is not None:
        found.append(_soft_located(shape, floor, cal.field_ut))
        steps, rest = _all_steps(u, t, r, np.hstack([q, q * (t >= shape.tau_s)[:, None]]), half, f2)
        steps = [s for s in steps if abs(s.tau_s - shape.tau_s) > half]
    steps = measure(u, t, r, q, f2, steps) if steps else steps
    steps, bursts = rest_of.bursts(steps, half, floor)
    steps = [s for s in steps if np.linalg.norm(np.linalg.solve(cal.soft_iron, s.d_h)) >= STEP_MIN_OVER_FLOOR * floor]
    found += [_step_located(s, cal, floor) for s in steps] + bursts
    return tuple(found) + tuple(rest_of.structure(u, t, rest, half, floor, rest_of.structure_window(half, res.clock)))


EFFECTS: tuple[Effect, ...] = (
    Effect(STEP, Kind.PHYSICS, search, remove_step, remove_trained=remove_step_trained),
    Effect(SOFT, Kind.PHYSICS, lambda res: (), remove_soft, remove_offset_change, remove_soft_trained),
)
