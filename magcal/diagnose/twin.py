"""The sensor twin: learn a SensorModel from a recording, draw twins of it, compare, name.

``learn`` turns a calibration (the deterministic part diagnosis or fit found) and the
recording's residuals into a :class:`~magcal.sim.model.SensorModel`: per-axis noise, the
quantum, one-sample glitches, degree-3/4 direction nonlinearity and a temperature gain when
held-out time blocks confirm them, intermittent disturbances of the field's magnitude,
saturation when the readings sit on a rail, and the offset and field wander as a fitted
spectrum (``magcal.sim.wander.fit``: a Whittle fit of band components, each seen through the
same calibration refit as the recording).

``compare`` is the parametric bootstrap: the recording's own times, channels and field
directions (recovered through the inverse model) drive ``draws`` twins of the model; each twin
is refitted with the same calibration model as the recording and the statistics of
``twin_stats`` computed on both. A statistic whose real value lies outside the 2.5–97.5 % band
of its twins is a mismatch; each is located (time blocks, direction cells, channel) and named
in physics words with the effect that would explain it.

``ladder`` runs the comparison for the baseline (hard iron + white noise) and for the model
with each effect added in turn, ending at the learned model.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from ..core.calibration import Calibration
from ..fit.ellipsoid import fit_ellipsoid
from ..fit.sphere import fit_sphere
from ..core.series import Series
from ..sim import directions
from ..sim import wander as wander_mod
from ..sim.disturbance import Disturbances
from ..sim.model import TEMP, Draws, SensorModel, replace_calibration
from ..sim.takes import Takes
from . import twin_stats as ts
from .twin_stats import repeats
from .twin_names import Mismatch, locate, mismatches
from . import twin_takes
from .lattice import quantum
from .model import Spec, fit_model

DRAWS = 50
BAND = (2.5, 97.5)
FOLDS = 5
BLOCKS = 40
CV_GAIN = 0.01  # a term must cut the held-out residual energy by at least 1 %
GLITCH_Z = 4.5  # a glitch departs from its neighbours by this many local noise σ
EVENT_Z = 4.5  # a disturbance departs from the median radius by this many robust σ at its peak
EVENT_EDGE = 2.0  # and lasts while it stays beyond this many
EVENT_MIN = 1  # and more than twice what a Gaussian residual would make
MAX_EVENTS = 64  # disturbance (size, duration) pairs kept in a model
P0_AXIS = 0.15  # chance that a random direction puts ≥ 90 % of its square on one axis (3 × (1 − √0.9))
TRAIN_WINDOW = 0.2  # a gap between spikes within ±20 % of the period counts as one period
TRAIN_Z = 5.0  # and the count there passes what random spikes give by this many σ
TRAIN_MIN = 20  # gaps needed to look for a period
TRAIN_READS = 4  # the shortest period sought, in read intervals
NOISE_LAG1_Z = 2.0  # the recording's lag-1 correlation must lie this many twin σ from the twins' mean
NOISE_LAG1_MAX = 0.45  # a one-step moving average reaches ±0.5
# channels that follow the orientation or are the magnetometer itself: not offered as couplings
ORIENTATION_WORDS = ("mag", "acc", "gyro", "quat", "roll", "pitch", "yaw", "bias", "att")


@dataclass(frozen=True)
class Residual:
    """One recording (real or twin) seen through a refitted calibration."""

    e: np.ndarray
    u: np.ndarray
    m: np.ndarray
    t: np.ndarray
    channels: Mapping[str, np.ndarray]
    gain: float | None = None


def _isotropic(w: np.ndarray) -> bool:
    return bool(np.max(np.abs(w / np.cbrt(np.linalg.det(w)) - np.eye(3))) < 1e-9)


def refit(model: SensorModel, m, t, channels, free: bool = True) -> Residual | None:
    """Refit ``model``'s kind of calibration (sphere or ellipsoid, with its channel terms) to
    the measurements and return their residual; None when the fit fails. ``free=False`` keeps
    the model's calibration (a recording whose motion cannot determine one, e.g. a still board)
    and only removes the mean level. A recording of takes (``model.takes``) has a level per
    take removed as well: each placement's own hard-iron surroundings, part of its calibration."""
    cal = model.calibration
    if not free:
        h = cal.correct(m, {c: channels[c] for c in cal.coef_ut_per_unit})
        norm = np.linalg.norm(h, axis=1)
        e = norm - norm.mean() if model.takes is None else model.takes.demean(norm, t)
        return Residual(e=e, u=h / norm[:, None], m=m, t=t, channels=channels, gain=None)
    soft = not _isotropic(cal.soft_iron)
    chans = tuple(cal.coef_ut_per_unit)
    used = {c: channels[c] for c in chans}
    if chans:
        f = fit_model(m, used, Spec(soft_iron=soft, channels=chans), cal.reference)
        if not f:
            return None
        fc = f.calibration()
        h = fc.correct(m, used)
        gain = ts.gain_of(fc.soft_iron) if soft else None
    else:
        f = fit_ellipsoid(m, kind="full") if soft else fit_sphere(m)
        if not f:
            return None
        h = (m - f.offset_ut) @ np.asarray(f.soft_iron).T
        gain = ts.gain_of(f.soft_iron) if soft else None
    norm = np.linalg.norm(h, axis=1)
    e = norm - np.sqrt(np.mean(norm * norm)) if chans else np.asarray(f.residual_ut)
    if model.takes is not None:
        e = model.takes.demean(e, t)
    return Residual(e=e, u=h / norm[:, None], m=m, t=t, channels=channels, gain=gain)


# -- learning ------------------------------------------------------------------------------
def _heldout_gain(e: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Coefficients of e on the columns of x (all data) and the held-out share of residual
    energy they remove: FOLDS folds of interleaved time blocks (BLOCKS blocks), so every fold
    sees most directions while the slow wander stays within a block."""
    n = len(e)
    fold = (np.arange(n) * BLOCKS // max(n, 1)) % FOLDS
    sse0 = sse1 = 0.0
    for k in range(FOLDS):
        idx = fold == k
        train = ~idx
        c = np.linalg.lstsq(x[train], e[train], rcond=None)[0]
        r = e[idx] - x[idx] @ c
        sse0 += float(e[idx] @ e[idx])
        sse1 += float(r @ r)
    coef = np.linalg.lstsq(x, e, rcond=None)[0]
    return coef, (sse0 - sse1) / max(sse0, 1e-300)


def _axis_noise(m: np.ndarray, white_var: float, u: np.ndarray, q: tuple) -> tuple:
    """Per-axis white noise: its shape from the second differences of the trajectory, its
    level from the white part of the radial residual, less the quantisation's share. ``u``:
    per sample, how a departure of the raw reading shows in the radial residual (Wᵀu)."""
    d2 = m[2:] - 2 * m[1:-1] + m[:-2]
    shape = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) * 1.4826 / np.sqrt(6.0)
    shape = np.where(shape > 0, shape, max(float(shape.max()), 1e-6))
    quant = np.asarray(q) ** 2 / 12.0
    radial_shape = float(np.mean(u * u @ (shape**2)))
    radial_quant = float(np.mean(u * u @ quant))
    level = max(white_var - radial_quant, 0.0) / max(radial_shape, 1e-300)
    return tuple(float(v) for v in shape * np.sqrt(level))


def _departure_score(g: np.ndarray) -> np.ndarray:
    """Per row of ``g`` (each sample's departure from its neighbours' mean, one column per
    component), the largest over the columns of the departure in units of the local noise (a
    running median over ±LOCAL samples, so fast motion raises the bar)."""
    a = np.abs(g - np.median(g, axis=0))
    local = ndimage.median_filter(a, size=(2 * ts.LOCAL + 1, 1), mode="nearest") / 0.6745
    floor = np.maximum(np.median(a, axis=0) / 0.6745, 1e-9)
    return np.max(a / np.maximum(local, 0.25 * floor), axis=1)


def spikes(m: np.ndarray, z: float | None = None, radius: np.ndarray | None = None,
           directions: np.ndarray | None = None) -> np.ndarray:
    """One-sample glitches: samples that depart from their neighbours' mean by more than
    ``z`` (GLITCH_Z) times the local noise, the largest of a run, and after which the series
    comes back — the neighbours agree with each other better than the sample agrees with them.
    Sought in the trajectory ``m`` (on some axis), or with ``radius`` (|h| per sample through a
    calibration) in |h| alone: a rotation keeps |h|, so a sharp turn of the board between two
    slow samples is not taken for a glitch, and fast motion, which raises the trajectory's
    local bar, does not hide one. With ``directions`` (the unit field directions per sample), a
    departure of |h| no larger than ``turn_blur`` allows beside a fast turn is the turn's, not a
    glitch."""
    z = GLITCH_Z if z is None else z
    hit = np.zeros(len(m), bool)
    if len(m) < 5:
        return hit
    x = np.asarray(m if radius is None else np.asarray(radius, dtype=np.float64)[:, None], dtype=np.float64)
    g = x[1:-1] - 0.5 * (x[:-2] + x[2:])
    score = _departure_score(g)
    peak = (score > z) & (score >= np.roll(score, 1)) & (score >= np.roll(score, -1))
    back = np.linalg.norm(x[2:] - x[:-2], axis=1) < np.linalg.norm(g, axis=1)
    hit[1:-1] = peak & back
    if radius is not None and directions is not None:
        hit[1:-1] &= np.abs(g[:, 0]) > turn_blur(directions, float(np.median(x)))[1:-1]
    return hit


def turn_blur(u: np.ndarray, radius_ut: float) -> np.ndarray:
    """Per sample, how far a turn can move |h| of a sample from its neighbours' mean (µT) when
    each reading is the field averaged over its read interval (a driver that accumulates
    conversions between reads, as ArduPilot's compass drivers do): a field of size
    ``radius_ut`` turning by θ at a steady rate along the shortest way averages to
    radius_ut·sin(θ/2)/(θ/2). θ: the largest step between reads (of the directions ``u``)
    among the two steps on each side, which feed the sample and its two neighbours. On a board
    turning a few degrees per read this is a few nT; at the flip that ends the ArduPilot Solo
    flight logged at 10 Hz (steps of 90–150° between reads) it is 10–20 µT, more than the dips
    of |h| there — dips the spike test had taken for glitches, and whose directions, re-drawn
    between neighbours 100° away, put a jump into every twin."""
    n = len(u)
    if n < 3:
        return np.zeros(n)
    step = np.arccos(np.clip(np.sum(u[1:] * u[:-1], axis=1), -1.0, 1.0))  # step j: u_j → u_j+1
    pad = np.concatenate([[0.0, 0.0], step, [0.0, 0.0]])  # step j at pad[j + 2]
    theta = np.max(np.stack([pad[0:n], pad[1 : n + 1], pad[2 : n + 2], pad[3 : n + 3]]), axis=0)
    return radius_ut * (1.0 - np.sinc(theta / (2.0 * np.pi)))


def _corrected(cal: Calibration, m: np.ndarray, chans: Mapping) -> np.ndarray:
    return cal.correct(m, {c: chans[c] for c in cal.coef_ut_per_unit})


def _radius(cal: Calibration, m: np.ndarray, chans: Mapping) -> np.ndarray:
    return np.linalg.norm(_corrected(cal, m, chans), axis=1)


def size_quantiles(size: np.ndarray) -> tuple:
    """The glitch sizes seen, as quantiles at evenly spaced probabilities over their 5–95 %
    range (``magcal.sim.model.glitch_sizes`` draws from them): five when there are enough to
    tell a shape, else the two ends (log-uniform between)."""
    if len(size) < 2:
        v = float(size[0]) if len(size) else 4.0
        return (v, v) if len(size) else (4.0, 15.0)
    k = 5 if len(size) >= 10 else 2
    q = np.quantile(size, np.linspace(0.05, 0.95, k)) if len(size) > 4 else np.array([size.min(), size.max()])
    return tuple(float(v) for v in np.maximum.accumulate(q))


def _glitches(m: np.ndarray, radius: np.ndarray, seen: np.ndarray | None = None,
              directions: np.ndarray | None = None, radial_share: float = 0.0) -> tuple[float, tuple, float, np.ndarray]:
    """(rate per sample, size quantiles µT, share along one sensor axis, the samples): the
    spikes of |h| (``spikes``). A glitch's size is read from its departure in |h| from its
    neighbours' mean, doubled (a jump in a random direction moves |h| by |cos θ| of its length,
    ½ on average): its departure in the 3-vector also carries the trajectory's own curvature,
    which on fast motion is many times the glitch (rm3100 umich flight: 3.9× the radial
    departure at the 90th percentile, 1.9× on its twins). A share ``radial_share`` of glitches
    along the field moves |h| by its whole length, so the departure is scaled by 2/(1 + share)
    (the mean |cos θ| of the mixture). A spike along one sensor axis a (≥
    90 % of its square there) is read, with ``seen`` (per sample Wᵀu, how a jump of the reading
    moves |h|), as its departure over |seen_a| (at most doubled): such a glitch moves |h| by its
    length times the field's share on that axis — on the estibone RM3100 logs, whose field lies
    near z, a z-axis glitch by 0.8 of it: doubled, it was read 1.6× too large. Axis share: the
    share of glitches with ≥ 90 % of their square on one axis, less the share a random
    direction would put there (P0_AXIS). ``directions``: the field's per sample, for ``spikes``
    to leave a fast turn's blur of |h| alone."""
    hit = spikes(m, radius=radius, directions=directions)
    k = np.flatnonzero(hit)
    if not len(k):
        return 0.0, (4.0, 15.0), 0.0, hit
    g = m[k] - 0.5 * (m[k - 1] + m[k + 1])
    size = np.linalg.norm(g, axis=1)
    along = np.max(g * g, axis=1) >= 0.9 * size**2
    one_axis = float(np.mean(along))
    share = float(np.clip((one_axis - P0_AXIS) / (1.0 - P0_AXIS), 0.0, 1.0))
    dep = _departures(radius, k)
    scale = np.full(len(k), 2.0 / (1.0 + radial_share))
    if seen is not None:  # a jump s along axis a moves |h| by s·(Wᵀu)_a
        axis = np.argmax(g * g, axis=1)
        scale[along] = 1.0 / np.maximum(np.abs(seen[k[along], axis[along]]), 0.5)
    return float(np.mean(hit)), size_quantiles(scale * dep), share, hit


def radial_fractions(h: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Per spike (``hit``) of the corrected readings ``h``, the share of its departure from its
    neighbours' mean (a vector) that lies along the field there (their mean's direction):
    1 for a glitch of the field's magnitude, 1/3 on average for a random direction (more among
    the spikes |h| shows, which favours those along the field)."""
    k = np.flatnonzero(hit[1:-1]) + 1
    g = h[k] - 0.5 * (h[k - 1] + h[k + 1])
    u = h[k - 1] + h[k + 1]
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    return np.sum(g * u, axis=1) ** 2 / np.maximum(np.sum(g * g, axis=1), 1e-300)


def twin_directions(model: SensorModel, series: Series) -> np.ndarray:
    """The field directions (n, 3) behind a recording, through the model's inverse, with each
    glitch sample re-drawn between the directions around it (the twin draws its own glitches;
    replayed, they would be there twice). When the model repeats reads, each of the
    recording's repeated reads keeps the direction of the read it repeats, bit for bit: the
    reads whose direction differs from the one before are the recording's conversions, which
    the twin replays one for one in its own pattern of repeats (``replayed``)."""
    chans = with_time(series)
    m = series.field_ut
    u = model.directions_of(m, {c: chans[c] for c in model.calibration.coef_ut_per_unit})
    bad = spikes(m, radius=_radius(model.calibration, m, chans), directions=u)
    again = repeats(m) if model.repeat_share > 0 else np.zeros(len(m), bool)
    bad &= ~again
    good = np.flatnonzero(~(bad | again))
    if bad.any() and len(good) >= 2:
        k = np.flatnonzero(bad)
        v = np.column_stack([np.interp(k, good, u[good, a]) for a in range(3)])
        u[k] = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    if again.any():
        u = u[np.maximum.accumulate(np.where(again, 0, np.arange(len(m))))]
    return u


def replayed(u: np.ndarray, shown: np.ndarray | None) -> np.ndarray:
    """The direction each of a twin's reads sees when the twin replays the recording's
    conversions one for one: ``u`` the recording's directions per read (``twin_directions``:
    a repeated read has the direction before it, bit for bit), ``shown`` the read whose
    conversion each of the twin's reads shows (``Draws.shown``; None: every read a conversion
    of its own, ``u`` as it is). The recording's reads less its own repeats are its sequence of
    conversions; the twin's conversions take them in order — a read the twin repeats re-reads
    the conversion before, and the next takes the next of the recording's, not the one two on
    (the steady turn of a board steps as far between conversions as the recording's do). The
    two counts differ a little (the repeats a still board or a coarse quantum make by chance
    are not in the model's share): the twin's conversion c takes the recording's nearest
    c·(C_rec − 1)/(C_twin − 1), never a direction between two (no chord across a pause)."""
    if shown is None or len(u) < 2:
        return u
    fresh = np.flatnonzero(~repeats(u))  # the recording's conversions
    conv = np.cumsum(shown == np.arange(len(shown))) - 1  # the twin's conversion at each read
    k = np.rint(conv * ((len(fresh) - 1) / max(int(conv[-1]), 1))).astype(np.int64)
    return u[fresh[k]]


def disturbances(e: np.ndarray, t: np.ndarray) -> tuple[Disturbances | None, np.ndarray, np.ndarray]:
    """(the disturbance process, the samples it covers, the residual with each of them
    replaced by the wander's level there, ``_beneath``) of a radial residual: stretches whose
    peak departs from the median by more than EVENT_Z robust σ, each extended while it stays
    beyond EVENT_EDGE σ. None unless there are at least EVENT_MIN and more than twice what a
    Gaussian residual of that σ would make (at 4.5σ, one in 150 000 samples); one event is
    enough to estimate a rate (1 per recording), and the twins then differ in how many they
    draw, as recordings of the same sensor would. Sizes and durations: ``event_pairs`` of the
    departures from the wander beneath them, lengths in samples × the sample period."""
    n = len(e)
    hit = np.zeros(n, bool)
    if n < 50:
        return None, hit, e
    a = e - np.median(e)
    sigma = max(1.4826 * float(np.median(np.abs(a))), 1e-12)
    edge = np.abs(a) > EVENT_EDGE * sigma
    d = np.diff(np.concatenate([[0], edge.astype(np.int8), [0]]))
    lo, hi = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    peaks = np.array([a[i:j][np.argmax(np.abs(a[i:j]))] for i, j in zip(lo, hi)]) if len(lo) else np.zeros(0)
    big = np.abs(peaks) > EVENT_Z * sigma
    expected = n * 2 * float(ndtr(-EVENT_Z))
    if big.sum() < max(EVENT_MIN, 2 * expected):
        return None, hit, e
    lo, hi, peaks = lo[big], hi[big], peaks[big]
    wander = np.array(a, dtype=np.float64)
    dep = []
    for i, j, v in zip(lo, hi, _beneath(a, lo, hi)):
        hit[i:j] = True
        dep.append(a[i:j] - v)
        wander[i:j] = v
    dt = wander_mod.sample_interval(t)  # samples to seconds at the rate the twin draws them back
    span = max(float(t[-1] - t[0]) + dt, dt)
    pairs = event_pairs(dep, dt)
    return Disturbances(rate_per_s=len(peaks) / span, size_ut=(float(pairs[:, 0].min()), float(pairs[:, 0].max())),
                        duration_s=(float(pairs[:, 1].min()), float(pairs[:, 1].max())),
                        up_share=float(np.mean(peaks > 0)), events=tuple(map(tuple, pairs))), hit, wander + np.median(e)


def _beneath(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list:
    """Per stretch a[lo:hi], the wander's level beneath it: the straight line from the median
    of the stretch's length of samples before it to the median of as many after it (samples
    of other stretches left out; one side alone when the other has none, 0 when neither)."""
    out = np.ones(len(a), bool)
    for i, j in zip(lo, hi):
        out[i:j] = False
    levels = []
    for i, j in zip(lo, hi):
        k = j - i
        before, after = a[max(i - k, 0):i][out[max(i - k, 0):i]], a[j:j + k][out[j:j + k]]
        left = float(np.median(before)) if len(before) else None
        right = float(np.median(after)) if len(after) else None
        left, right = (left if left is not None else right), (right if right is not None else left)
        levels.append(np.linspace(left or 0.0, right or 0.0, k))
    return levels


def event_pairs(dep: list, dt_s: float) -> np.ndarray:
    """(k, 2): size µT and duration s of the disturbances whose departures from the wander
    beneath them are ``dep`` (samples ``dt_s`` apart). Each is read as the hold of equal
    energy — its RMS departure for its length — so that the process gives back the power the
    stretches take out of the residual the wander is fitted to: a stretch is a bump that rises
    through the edge to its peak and falls back, and a hold at its peak for its whole length
    carried 4.4× its energy on hmc5843 ucalgary. Kept as pairs (the twin draws one pair per
    event): sizes and durations drawn apart, each log-uniform over its 5–95 % range, lost how
    they go together and the few longest holds, which carry most of the power. At most
    MAX_EVENTS, at evenly spaced ranks of energy."""
    pairs = np.array([(max(np.sqrt(np.mean(x**2)), 1e-12), len(x) * dt_s) for x in dep])
    if len(pairs) > MAX_EVENTS:
        order = np.argsort(pairs[:, 0] ** 2 * pairs[:, 1], kind="stable")
        pairs = pairs[order[np.round(np.linspace(0, len(pairs) - 1, MAX_EVENTS)).astype(np.int64)]]
    return pairs


def glitch_train(t_spikes: np.ndarray, read_s: float) -> dict:
    """{glitch_period_s, glitch_jitter_s} when the spikes come nearly periodically, else {}:
    the gaps between successive spikes pile up within ±TRAIN_WINDOW of one period — more, by
    TRAIN_Z σ, than the mean of the two windows of the same width either side (what a smooth
    density of gaps puts there: spikes at random times, or in bursts, make no peak) — a high
    bar, since every gap seen is tried as the period. Periods under TRAIN_READS read intervals
    ``read_s`` are not sought (a burst of spikes two reads apart is not a train). The period:
    the median of the gaps in its window; the jitter: their spread over √2 (a gap is the
    difference of two pulses' times, each off its slot). A pulse the detector missed makes a
    gap of two periods, outside the window."""
    t = np.sort(np.asarray(t_spikes, dtype=np.float64))
    gaps = np.diff(t)
    gaps = gaps[gaps > 0]
    c = np.unique(gaps[gaps >= TRAIN_READS * read_s])
    if len(gaps) < TRAIN_MIN or not len(c):
        return {}
    g = np.sort(gaps)
    w = TRAIN_WINDOW * c

    def within(half):  # gaps within ``half`` of each candidate (counted on the sorted gaps)
        return np.searchsorted(g, c + half, side="right") - np.searchsorted(g, c - half, side="left")

    inside = within(w)
    beside = (within(3 * w) - inside) / 2.0
    z = (inside - beside) / np.sqrt(inside + beside / 2.0 + 1.0)
    best = int(np.argmax(z))
    if z[best] < TRAIN_Z:
        return {}
    sel = gaps[np.abs(gaps - c[best]) <= TRAIN_WINDOW * c[best]]
    period = float(np.median(sel))
    return {"glitch_period_s": period, "glitch_jitter_s": float(min(np.std(sel) / np.sqrt(2.0), 0.5 * period))}


def _saturation(m: np.ndarray) -> float | None:
    top = np.max(np.abs(m))
    at_rail = np.isclose(np.abs(m), top, rtol=0, atol=1e-9 + 1e-6 * top)
    return float(top) if np.count_nonzero(at_rail) >= max(5, 0.002 * len(m)) else None


def learn(series: Series, calibration: Calibration, source: Mapping | None = None, free: bool = True) -> SensorModel:
    """The SensorModel of ``series`` around ``calibration`` (its deterministic part).
    ``free=False``: the calibration came from elsewhere and the motion cannot determine one
    (a still board); direction terms are not sought and the refit only removes the level.
    A recording of takes (``placements``) is learned again with a level per take removed."""
    model = _learn(series, calibration, source, free)
    takes = placements(model, series.only_valid(), free)
    return model if takes is None else _learn(series, calibration, source, free, takes)


TAKE_SEEDS = tuple(range(201, 209))


def placements(model: SensorModel, series: Series, free: bool = True) -> Takes | None:
    """The takes of a recording (``twin_takes``) when its level steps at their starts more than
    the twins of ``model`` (learned without takes) step there, with the spread of its levels
    between them; else None."""
    real = refit(model, series.field_ut, series.t_s, with_time(series), free)
    takes = None if real is None else twin_takes.candidate(real.u, real.t)
    if takes is None:
        return None
    u = twin_directions(model, series)
    twins = [twin_draw(model, series, seed, free, u) for seed in TAKE_SEEDS]
    steps = [twin_takes.level_steps(x.e, x.t, takes) for x in twins if x is not None]
    if not twin_takes.steps_exceed(twin_takes.level_steps(real.e, real.t, takes), steps):
        return None
    return twin_takes.with_levels(takes, real.e, real.t)


def _learn(series: Series, calibration: Calibration, source: Mapping | None, free: bool,
           takes: Takes | None = None) -> SensorModel:
    """``learn`` with the takes given (None: one take)."""
    s = series.only_valid()
    m, t, chans = s.field_ut, s.t_s, with_time(s)
    q = quantum(m)
    h_all = _corrected(calibration, m, chans)
    r_all = np.linalg.norm(h_all, axis=1)
    u_all = h_all / r_all[:, None]
    seen_all = u_all @ np.asarray(calibration.soft_iron)  # how a jump of the reading moves |h|
    rate, size, axis_share, hit = _glitches(m, r_all, seen_all, u_all)
    keep = ~hit
    used = {c: chans[c][keep] for c in calibration.coef_ut_per_unit}
    h = calibration.correct(m[keep], used)
    r = np.linalg.norm(h, axis=1)
    u = h / r[:, None]
    e = r - calibration.field_ut
    e = e - e.mean()
    e = e if takes is None else takes.demean(e, t[keep])  # each placement's level is its calibration's
    nonlin = np.zeros(len(directions.NAMES))
    coef, gain = _heldout_gain(e, directions.basis(u)) if free else (nonlin, 0.0)
    if gain > CV_GAIN:
        nonlin = coef
        e = e - directions.basis(u) @ coef
    temp_gain, temp_ref = 0.0, 25.0
    if TEMP in chans:
        temp_ref = float(np.median(chans[TEMP]))
        x = ((chans[TEMP][keep] - temp_ref) * calibration.field_ut)[:, None]
        c, g = _heldout_gain(e, x)
        if g > CV_GAIN:
            temp_gain, e = float(c[0]), e - x[:, 0] * float(c[0])
    dist, _, e = disturbances(e, t[keep])  # the wander is fitted with each replaced by its level
    e = e - e.mean()
    # the noise, the quantum and the offset wander enter the raw reading, which the residual
    # sees through the soft iron: |W(m − b)| moves by (Wᵀu)·δ for a departure δ of m
    seen = u @ np.asarray(calibration.soft_iron)
    comps, white = wander_mod.fit(e, seen, t[keep], _refit_projector(u, used, takes, t[keep], free))
    model = SensorModel(
        calibration=replace_calibration(calibration, field_ut=calibration.field_ut + float(np.mean(r - calibration.field_ut))),
        noise_ut=_axis_noise(m[keep], white, seen, q), quantum_ut=q, wander=comps,
        glitch_rate=rate, glitch_ut=size, glitch_axis_share=axis_share, **glitch_train(t[hit], wander_mod.sample_interval(t)),
        disturbances=dist, nonlinearity_ut=tuple(nonlin),
        temp_gain_per_c=temp_gain, temp_ref_c=temp_ref, saturation_ut=_saturation(m), takes=takes,
        rate_hz=1.0 / wander_mod.sample_interval(t), source=dict(source or {}),
    )
    model = replace(model, repeat_share=repeat_share(model, s))
    if rate > 0:
        rate, missed = glitch_process(model, s, hit)
        glitched, missed = along_the_field(replace(model, glitch_rate=rate), s, hit, h_all, missed,
                                           lambda share: _glitches(m, r_all, seen_all, u_all, share)[1])
        model = replace(glitched, noise_ut=_less_noise(model, s, missed))
    model = replace(model, noise_lag1=noise_lag1(model, s, free))
    # once more with the final glitches and noise: both set how many reads repeat by chance and
    # how many of the model's repeats a glitch breaks (learned before them, the twins of rm3100
    # estibone test0 repeated 0.213–0.218 of their reads against the recording's 0.236)
    return replace(model, repeat_share=repeat_share(model, s))


def noise_lag1(model: SensorModel, series: Series, free: bool = True, seeds=tuple(range(101, 113))) -> float:
    """The correlation between successive reads' noise that brings the twins' lag-1
    correlation of the residual to the recording's — 0 (white) unless the recording's lies
    beyond NOISE_LAG1_Z of the twins' spread. Every other effect (wander, repeats, glitches)
    is already in the twins, so what is left at lag 1 is the noise's own: it moves the
    residual's lag-1 correlation by its share of the residual's variance. A gap the noise
    could close only with a correlation beyond NOISE_LAG1_MAX is left to the effects that made
    it (0)."""
    real = refit(model, series.field_ut, series.t_s, with_time(series), free)
    u = twin_directions(model, series)
    twins = [twin_draw(model, series, seed, free, u) for seed in seeds]
    twins = [x for x in twins if x is not None]
    if real is None or len(twins) < 2:
        return 0.0
    lag = np.array([ts.lag1(x.e) for x in twins])
    gap = ts.lag1(real.e) - float(np.mean(lag))
    if abs(gap) <= NOISE_LAG1_Z * float(np.std(lag, ddof=1)):
        return 0.0
    rho = gap * float(np.mean([np.var(x.e) for x in twins])) / max(_white_var(model, series, u), 1e-300)
    return float(rho) if abs(rho) <= NOISE_LAG1_MAX else 0.0  # beyond what the noise can carry: not the noise's


def _less_noise(model: SensorModel, series: Series, missed: float) -> tuple:
    """The white noise less the glitches the detector missed: those stayed in the residual the
    wander and its white floor were fitted to, and the twin draws them again as glitches (on
    rm3100 umich flight the twins' RMS came out above the recording's). Cut to no less than a
    tenth of its variance."""
    sigma, white = np.asarray(model.noise_ut), _white_var(model, series)
    if white <= 0 or missed <= 0:
        return model.noise_ut
    return tuple(float(v) for v in sigma * np.sqrt(max(white - missed, 0.1 * white) / white))


def _white_var(model: SensorModel, series: Series, u: np.ndarray | None = None) -> float:
    """The radial variance µT² of the model's white noise along the recording's directions
    (``u``: ``twin_directions``, when the caller has them)."""
    u = (twin_directions(model, series) if u is None else u) @ np.asarray(model.calibration.soft_iron)
    return float(np.mean(u * u @ np.asarray(model.noise_ut) ** 2))


# the repeats' gate, as wide as the comparison's band (and NOISE_LAG1_Z): at three σ a recording
# with a few repeats more than chance (qmc5883l tomisuarez filtered 3 in 22745 reads, twins 0;
# ardupilot MAG 41 in 2384, chance about 25) got none and its comparison then called them missing
REPEAT_Z = 2.0
REPEAT_STEPS = 3  # at most this many Newton steps of the repeat share (each a pair of twins)


def _twin_repeats(model: SensorModel, series: Series, seeds) -> float:
    """The share of repeated reads in ``model``'s twins of ``series`` (its glitches too: a
    glitch on a repeated read breaks the repeat, in the recording as in the twin)."""
    chans, u = with_time(series), twin_directions(model, series)
    return float(np.mean([np.mean(repeats(twin_readings(model, u, series.t_s, chans, seed)[0])) for seed in seeds]))


def repeat_share(model: SensorModel, series: Series, seeds=(1, 2)) -> float:
    """The share of reads that repeat the previous conversion (the host read before the next
    one was ready): the recording's share of exact repeats beyond what its twins without
    repeats make by chance (a coarse quantum and a still board repeat a reading too), when it
    passes that chance share by REPEAT_Z binomial σ (the recording's and the twins' own count
    both counted); else 0.

    That first share is low: the twins without repeats read the recording's repeated reads
    at the direction before them, where noise alone repeats a reading far more often than after
    a turn, so they overstate chance. The twins with the share replay fresh conversions there;
    their chance repeats beside the share's own (c) set the step towards the share that makes
    the twins repeat as often as the recording (Newton on s + (1 − s)·c). Without these steps
    the twins of five of the seven real recordings with repeats repeated 4–16 % fewer reads
    than their recordings."""
    n = len(series.field_ut)
    seen = float(np.mean(repeats(series.field_ut)))
    if seen == 0.0:
        return 0.0
    chance = _twin_repeats(replace(model, repeat_share=0.0), series, seeds)
    spread = np.sqrt(max(chance * (1.0 - chance), 1.0 / n) / n * (1.0 + 1.0 / len(seeds)))
    if seen <= chance + REPEAT_Z * spread:
        return 0.0
    share = min((seen - chance) / (1.0 - chance), 0.9)
    for _ in range(REPEAT_STEPS):
        made = _twin_repeats(replace(model, repeat_share=share), series, seeds)
        if abs(made - seen) < 1.0 / n:
            break
        c = max((made - share) / (1.0 - share), 0.0)
        share = float(np.clip(share + (seen - made) / (1.0 - c), 0.0, 0.9))
    return float(share)


GLITCH_SEEDS = (1, 2, 3, 4)


def _departures(r: np.ndarray, k: np.ndarray) -> np.ndarray:
    """|r_k − mean of its neighbours| (µT) at samples ``k``: a spike's departure in |h|."""
    return np.abs(r[k] - 0.5 * (r[k - 1] + r[k + 1]))


def _spike_counter(model: SensorModel, series: Series, seeds=GLITCH_SEEDS):
    """rate ↦ (mean number of spikes ``spikes`` finds, the radial variance µT² of the glitches
    it misses, the spikes' ``radial_fractions``) on twins of ``series`` whose glitches come at ``rate``. The twins' other random
    parts are drawn once and the glitches from fixed generators (common random numbers): a
    higher rate adds glitches where a lower one had them, so the count rises with the rate and
    a bracketing solve converges."""
    chans, u = with_time(series), twin_directions(model, series)
    bare = model.without("glitches")
    base = [twin_draws(bare, u, series.t_s, seed) for seed in seeds]  # (directions seen, draws) per seed
    seen = [v @ np.asarray(model.calibration.soft_iron) for v, _ in base]  # a jump g of m moves |h| by seen·g

    def count(rate: float) -> tuple[float, float, np.ndarray]:
        n_hit, missed, fractions = 0, 0.0, []
        for seed, (v, d), w in zip(seeds, base, seen):
            rng = np.random.default_rng([seed, 0x611])
            g, along = model.glitch_vectors(rng, series.t_s, seed, rate)
            m, _ = bare.distort(v, chans, replace(d, glitch_ut=g, glitch_along_ut=along))
            h = _corrected(bare.calibration, m, chans)
            hit = spikes(m, radius=np.linalg.norm(h, axis=1), directions=v)
            n_hit += int(np.count_nonzero(hit))
            moved = np.sum(g * w, axis=1) + (0.0 if along is None else along)  # a glitch along the field moves |h| by its size
            missed += float(np.sum(moved[~hit] ** 2)) / len(v)
            fractions.append(radial_fractions(h, hit))
        return n_hit / len(seeds), missed / len(seeds), np.concatenate(fractions)

    return count


def _rate_for(count, observed: float, n: int, steps: int = 12, top: float | None = None) -> float | None:
    """The rate at which the twins' spike count equals ``observed`` (bisection; the count
    rises with the rate), or None when even a glitch in every other sample falls short (the
    sizes are too small for the detector to see); ``top``: the highest rate there is (a pulse
    train's every pulse), returned when the count falls short there."""
    ceiling = 0.5 if top is None else top
    lo, hi = 0.0, min(max(2.0 * observed / n, 1e-4), ceiling)
    while count(hi)[0] < observed:
        if hi >= ceiling:
            return top
        lo, hi = hi, min(2.0 * hi, ceiling)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if count(mid)[0] < observed else (lo, mid)
    return 0.5 * (lo + hi)


def glitch_process(model: SensorModel, series: Series, hit: np.ndarray) -> tuple[float, float]:
    """(rate per sample, the radial variance µT² of the glitches the detector misses) of the
    glitches, at the model's sizes, that make the twins' detector find as many spikes as it
    finds on the recording. The detector misses glitches near the noise and finds a few spikes
    where there are none (its false positives: the count on glitch-free twins), so the rate
    seen is not the rate to draw; both are measured on twins of the recording (its times,
    directions and every other effect) and the rate solved by bisection — no rate when the
    recording shows no more spikes than glitch-free twins make, within three Poisson σ. A pulse
    train cannot glitch more reads than it has pulses: when even a glitch at every pulse falls
    short, every pulse glitches (the nearest the train comes)."""
    observed = float(np.count_nonzero(hit))
    count = _spike_counter(model, series)
    null = count(0.0)[0]
    if observed <= null + 3.0 * np.sqrt(max(null, 1.0)):
        return 0.0, 0.0
    full = None if model.glitch_period_s is None else min(1.0 / (model.rate_hz * model.glitch_period_s), 0.5)
    rate = _rate_for(count, observed, len(hit), top=full)
    if rate is None:
        return model.glitch_rate, 0.0  # the detector cannot place them: keep the rate it saw
    return float(min(rate, 0.5)), count(rate)[1]


def along_the_field(model: SensorModel, series: Series, hit: np.ndarray, h: np.ndarray, missed: float,
                    sizes) -> tuple[SensorModel, float]:
    """(the model with the share of its glitches that lie along the field, the radial variance
    µT² of the glitches the detector misses). The spikes of |h| favour glitches along the field
    even when their directions are random, so the recording's mean ``radial_fractions`` (its
    spikes ``hit`` of the corrected readings ``h``) is set against the twins': at the model's
    rate with no glitch along the field, and with every glitch not on a sensor axis along it
    (``sizes(share)``: the size quantiles read for a share, the rate solved again); the share
    is interpolated between the two (none when the recording's mean is not above the first
    twins'; as the axis share, an estimate clipped to its range, with no test). A glitch along the field moves |h| by
    its whole length and the trajectory by no more, where a random one of the same departure
    in |h| is twice as long on average: drawn in random directions, such glitches gave the
    ArduPilot Solo twins isolated 3-vector jumps the recording lacks."""
    seen = radial_fractions(h, hit)
    if not len(seen) or model.glitch_rate <= 0:
        return model, missed
    none = _spike_counter(model, series)(model.glitch_rate)[2]
    if not len(none) or np.mean(seen) <= np.mean(none):
        return model, missed

    def solved(share: float) -> tuple[SensorModel, float, np.ndarray]:
        m = replace(model, glitch_radial_share=share, glitch_ut=sizes(share))
        rate, lost = glitch_process(m, series, hit)
        m = replace(m, glitch_rate=rate)
        return m, lost, _spike_counter(m, series)(rate)[2]

    top = 1.0 - model.glitch_axis_share
    full, lost, every = solved(top)
    if not len(every) or np.mean(every) <= np.mean(none):
        return full, lost
    share = top * float(np.clip((np.mean(seen) - np.mean(none)) / (np.mean(every) - np.mean(none)), 0.0, 1.0))
    if share >= top:
        return full, lost
    out, lost, _ = solved(share)
    return out, lost


def projector(u: np.ndarray, channels: Mapping[str, np.ndarray], then=None):
    """x ↦ what is left of a radial series x once a calibration is refitted: the residual of
    its least squares on the linearised model (offset, radius, soft iron: the degree ≤ 2
    functions of the direction; and x_c·u per channel term) — and then ``then`` of what is left
    (a level per take, ``Takes.demean``), in that order, as ``refit`` removes them."""
    cols = [np.ones(len(u)), *u.T, *(u[:, [0, 0, 1]] * u[:, [1, 2, 2]]).T, *(u[:, :2] ** 2).T]  # z² = 1 − x² − y²
    for x in channels.values():
        xc = x - np.mean(x)
        cols += [xc * u[:, a] for a in range(3)]
    q, _ = np.linalg.qr(np.column_stack(cols))

    def project(x: np.ndarray) -> np.ndarray:
        left = x - q @ (q.T @ x)
        return left if then is None else then(left)

    return project


def _refit_projector(u: np.ndarray, channels: Mapping, takes, t: np.ndarray, free: bool):
    """What ``refit`` leaves of a radial series, linearised (``projector``; a fixed
    calibration removes only the level, per take when there are takes)."""
    per_take = None if takes is None else (lambda x: takes.demean(x, t))
    return projector(u, channels, per_take) if free else per_take


# -- the comparison -------------------------------------------------------------------------
def with_time(series: Series) -> dict:
    """The recording's channels, plus time (``t_s``) for a model with a drift term."""
    chans = dict(series.channels)
    chans.setdefault("t_s", series.t_s)
    return chans


@dataclass(frozen=True)
class Band:
    """A statistic of the recording against the spread of its twins."""

    name: str
    real: float
    low: float
    high: float
    median: float

    @property
    def inside(self) -> bool:
        return bool(self.low <= self.real <= self.high) if np.isfinite(self.real) else True

    @property
    def side(self) -> str:
        return "inside" if self.inside else ("high" if self.real > self.high else "low")

    def to_dict(self) -> dict:
        return {"real": _num(self.real), "twin_low": _num(self.low), "twin_high": _num(self.high),
                "twin_median": _num(self.median), "inside": self.inside}


@dataclass(frozen=True)
class Comparison:
    step: str
    effects: tuple
    bands: tuple
    mismatches: tuple
    draws: int
    located: dict = field(default_factory=dict, repr=False)  # real and twin-band pieces
    real: Residual | None = field(default=None, repr=False)
    twin: Residual | None = field(default=None, repr=False)  # one twin draw, for pictures

    @property
    def inside(self) -> int:
        return sum(b.inside for b in self.bands)

    def to_dict(self) -> dict:
        return {"step": self.step, "effects": list(self.effects), "draws": self.draws,
                "inside": self.inside, "statistics": len(self.bands),
                "bands": {b.name: b.to_dict() for b in self.bands},
                "mismatches": [m.to_dict() for m in self.mismatches]}


def _num(x):
    x = float(x)
    return x if np.isfinite(x) else None


def twin_draws(model: SensorModel, u: np.ndarray, t: np.ndarray, seed: int) -> tuple[np.ndarray, Draws]:
    """(the direction each read sees, the random parts) of a twin driven along the
    recording's directions ``u``, its conversions ``replayed`` in the twin's pattern of
    repeats. Those directions came through the inverse model from the recording's readings,
    so they already carry the part of its white noise and offset wander that lies across the
    field (the inverse keeps it, only |h| is normalised away); the twin draws those two along
    the field alone — the gradient of |W(m − b)|, Wᵀu — or the part across the field would be
    there twice and the twin's trajectory rougher than the recording's (its jumps then hide
    among the noise)."""
    d = model.draws(t, seed)
    u = replayed(u, d.shown)
    v = u @ np.asarray(model.calibration.soft_iron)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    sigma = np.asarray(model.noise_ut)
    along = np.sum(d.noise * sigma * v, axis=1, keepdims=True) * v
    noise = np.where(sigma > 0, along / np.where(sigma > 0, sigma, 1.0), 0.0)
    wander = np.sum(d.wander_ut * v, axis=1, keepdims=True) * v
    return u, replace(d, noise=noise, wander_ut=wander)


def twin_readings(model: SensorModel, u: np.ndarray, t: np.ndarray, chans: Mapping, seed: int):
    """(m, valid): ``model``'s twin along the recording's directions ``u`` (``twin_draws``)."""
    seen, draws = twin_draws(model, u, t, seed)
    return model.distort(seen, chans, draws)


def twin_draw(model: SensorModel, series: Series, seed: int, free: bool = True, u=None) -> Residual | None:
    """One twin of ``series`` refitted: the recording's times, channels and directions
    (``twin_directions``, or ``u`` when given)."""
    chans = with_time(series)
    u = twin_directions(model, series) if u is None else u
    m, valid = twin_readings(model, u, series.t_s, chans, seed)
    if not valid.all():
        m, chans = m[valid], {k: v[valid] for k, v in chans.items()}
    return refit(model, m, series.t_s[valid], chans, free)


def compare(model: SensorModel, series: Series, draws: int = DRAWS, seed: int = 0, step: str = "final",
            free: bool = True) -> Comparison:
    """The parametric bootstrap of ``model`` against ``series`` (valid samples). A statistic
    the recording cannot give (NaN: e.g. direction terms on a still board) is left out."""
    s = series.only_valid()
    chans = with_time(s)
    real = refit(model, s.field_ut, s.t_s, chans, free)
    if real is None:
        raise ValueError("the model's calibration cannot be refitted to the recording")
    shown = {k: v for k, v in s.channels.items() if not any(w in k.lower() for w in ORIENTATION_WORDS)}
    again = bool(repeats(real.m).any())
    stats_real, loc_real = ts.battery(real.e, real.u, real.m, real.t, shown, real.gain if free else float("nan"), again)
    stats_real = {k: v for k, v in stats_real.items() if np.isfinite(v)}
    sims, locs, first = [], [], None
    u = twin_directions(model, s)
    for i in range(draws):
        x = twin_draw(model, s, seed + i, free, u)
        if x is None:
            continue
        first = first or x
        st, lo = ts.battery(x.e, x.u, x.m, x.t, {k: x.channels[k] for k in shown}, x.gain if free else float("nan"),
                            again)
        sims.append(st)
        locs.append(lo)
    bands = tuple(_band(k, v, [d.get(k, np.nan) for d in sims]) for k, v in stats_real.items())
    located = locate(loc_real, locs, s.t_s)
    return Comparison(step=step, effects=model.effects(), bands=bands,
                      mismatches=mismatches(bands, located), draws=len(sims), located=located,
                      real=real, twin=first)


def _band(name: str, real: float, values) -> Band:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return Band(name, real, -np.inf, np.inf, float("nan"))
    lo, mid, hi = np.percentile(v, [BAND[0], 50.0, BAND[1]])
    return Band(name, float(real), float(lo), float(hi), float(mid))


# -- baseline → each effect added → final ---------------------------------------------------
ORDER = ("calibration", "quantum", "wander", "field_wander", "nonlinearity", "temperature_gain", "glitches",
         "disturbances", "saturation", "repeats")
_LATER = {step: ORDER[i + 1:] for i, step in enumerate(ORDER)}  # what a step still leaves out


@dataclass(frozen=True)
class TwinReport:
    """The comparison of each step, baseline first, the learned model last."""

    model: SensorModel
    steps: tuple

    @property
    def final(self) -> Comparison:
        return self.steps[-1]

    @property
    def baseline(self) -> Comparison:
        return self.steps[0]

    def to_dict(self) -> dict:
        return {"version": 1, "draws": self.final.draws, "band_pct": list(BAND),
                "steps": [c.to_dict() for c in self.steps], "model": self.model.to_dict()}


def baseline_model(model: SensorModel, series: Series, free: bool = True) -> SensorModel:
    """Hard iron + white noise: the sphere fitted to the recording (or, when the recording
    cannot determine one, the model's offset and field), its RMS as the noise."""
    m = series.only_valid().field_ut
    f = fit_sphere(m) if free else None
    if free and not f:
        raise ValueError(f"cannot fit the baseline sphere: {f}")
    if f:
        cal, rms = Calibration(offset_ut=f.offset_ut, field_ut=f.field_ut), f.rms_ut
    else:
        cal = Calibration(offset_ut=model.calibration.offset_ut, field_ut=model.calibration.field_ut)
        r = np.linalg.norm(m - cal.offset_ut, axis=1)
        rms = float(np.std(r))
    return SensorModel(calibration=cal, noise_ut=(rms,) * 3, rate_hz=model.rate_hz)


def _white(model: SensorModel, series: Series, free: bool = True) -> SensorModel:
    """``model`` with its noise raised to carry all of the residual a model without wander
    leaves (so the step is judged on its shape, not on a missing variance)."""
    s = series.only_valid()
    real = refit(model, s.field_ut, s.t_s, with_time(s), free)
    if real is None:
        return model
    quant = float(np.mean(real.u**2 @ (np.asarray(model.quantum_ut) ** 2 / 12.0)))
    extra = float(np.var(real.e)) - quant - float(np.mean(directions.radial_ut(real.u, model.nonlinearity_ut) ** 2))
    return replace(model, noise_ut=(float(np.sqrt(max(extra, 1e-12))),) * 3)


def step_models(model: SensorModel, series: Series, free: bool = True) -> list[tuple[str, SensorModel]]:
    """(name, model) from the baseline through each effect the learned model carries."""
    has = set(model.effects()) | ({"quantum"} if any(model.quantum_ut) else set())
    out = [("baseline", baseline_model(model, series, free))]
    for step in ORDER:
        present = has & {"soft_iron", "takes", *model.calibration.coef_ut_per_unit} if step == "calibration" else has & {step}
        if not present:
            continue
        m = model
        for later in _LATER[step]:
            if later in has:
                m = m.without(later)
        if not {"wander", "field_wander"} & set(m.effects()):
            m = _white(m, series, free)
        out.append(("+" + step if _LATER[step] and any(x in has for x in _LATER[step]) else "final", m))
    if out[-1][0] != "final":
        out.append(("final", model))
    return out


def ladder(model: SensorModel, series: Series, draws: int = DRAWS, seed: int = 0, free: bool = True) -> TwinReport:
    """Compare each step with the recording on the same seeds."""
    steps = tuple(compare(m, series, draws, seed, name, free) for name, m in step_models(model, series, free))
    return TwinReport(model=model, steps=steps)
