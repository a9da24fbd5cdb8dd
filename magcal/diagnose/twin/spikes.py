"""One-sample glitches in a recording: where they are (``spikes``), how large, how many lie
along one sensor axis, and whether they come as a periodic train (``glitch_train``).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from . import stats as ts


GLITCH_Z = 4.5  # a glitch departs from its neighbours by this many local noise σ
P0_AXIS = 0.15  # chance that a random direction puts ≥ 90 % of its square on one axis (3 × (1 − √0.9))
TRAIN_WINDOW = 0.2  # a gap between spikes within ±20 % of the period counts as one period
TRAIN_Z = 5.0  # and the count there passes what random spikes give by this many σ
TRAIN_MIN = 20  # gaps needed to look for a period
TRAIN_READS = 4  # the shortest period sought, in read intervals


def _departure_score(g: np.ndarray) -> np.ndarray:
    """Per row of ``g`` (each sample's departure from its neighbours' mean, one column per
    component), the largest over the columns of the departure in units of the local noise (a
    running median over ±LOCAL samples, so fast motion raises the bar; taken column by column,
    where scipy's one-dimensional median filter is ~10x faster than a (2·LOCAL+1, 1) window on
    the whole array and gives the same values)."""
    a = np.abs(g - np.median(g, axis=0))
    local = np.column_stack([ndimage.median_filter(a[:, k], size=2 * ts.LOCAL + 1, mode="nearest")
                             for k in range(a.shape[1])]) / 0.6745
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


def find_glitches(m: np.ndarray, radius: np.ndarray, seen: np.ndarray | None = None,
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


def _departures(r: np.ndarray, k: np.ndarray) -> np.ndarray:
    """|r_k − mean of its neighbours| (µT) at samples ``k``: a spike's departure in |h|."""
    return np.abs(r[k] - 0.5 * (r[k - 1] + r[k + 1]))


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
