"""Slow, correlated departures of the reading: the offset wander and the field wander.

Real residuals are not white (docs/sensor-model.md). Two processes, each a sum of independent
stationary Gaussian components:

* the **offset wander** (``frame="offset"``): a vector in the sensor frame added to every
  reading — temperature the sensor does not report, a magnetised part relaxing. The radial
  residual sees it through the field direction, u·w(t).
* the **field wander** (``frame="field"``): a change of the field's magnitude — the board
  carried through a field gradient, iron moving nearby. The radial residual sees all of it,
  whatever the direction.

A component's spectrum is either an Ornstein–Uhlenbeck (Lorentzian) one, correlation time
``tau_s``::

    cov(w(t), w(t + Δ)) = σ² exp(−|Δ| / τ)

or flat between two frequencies, ``band_hz = (f_lo, f_hi)``::

    cov(w(t), w(t + Δ)) = σ² [sin 2πf_hiΔ − sin 2πf_loΔ] / (2π (f_hi − f_lo) Δ)

A sum of band components over log-spaced bands is a fitted spectrum of any shape (a hump where
the hand's motion lives, a steep fall above it, a narrow line); that is what ``fit`` learns.

Drawing, two samplers of the one process: ``draw`` synthesises each component from its
spectrum as a sum of cosines (frequencies at stratified quantiles of the spectrum, random
phases, equal amplitudes σ·√(2/K)): every value is a function of (seed, t) alone, so the
simulated board can be sampled at any time, in any order, and reproduced. ``draw_path`` makes
a whole stream at once (a twin of a recording): the exact AR(1) recursion for an OU component,
Fourier synthesis on a padded grid for the band components.

Fitting (``fit``): the radial residual e_i of a recording after its calibration is refitted
is, to first order, u_i·w(t_i) + f(t_i) + white noise, less what the refit absorbs. Each
candidate component (every band, in each frame) is drawn with unit σ on the recording's own
times and directions and projected as the refit would; its mean periodogram in log-spaced
frequency bins is its spectrum as the residual shows it (simulated moments). The variances
σ_k² ≥ 0 and the white variance maximise the Whittle likelihood of the residual's binned
periodogram; components carrying little variance are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from .nnls import nnls  # numpy: scipy.optimize costs a command 0.4 s to import

K_COSINES = 48  # cosines per component and axis (``draw``)
MIN_SHARE = 0.01  # a component below this share of the fitted spectral density in its own band is dropped
MIN_LEFT = 0.25  # a candidate the calibration refit absorbs beyond this share is not identifiable
OFFSET, FIELD = "offset", "field"
BANDS_PER_DECADE = 4
FIELD_TOP = 0.25  # the field wander's highest band ends at this share of the Nyquist frequency
MAX_GRID = 1 << 22  # points of the Fourier grid of draw_path


@dataclass(frozen=True)
class WanderComponent:
    """One component: stationary σ (µT; per sensor axis for the offset, of |field| for the
    field), and its spectrum — an OU correlation time ``tau_s`` or a flat band ``band_hz``."""

    sigma_ut: tuple
    tau_s: float | None = None
    band_hz: tuple | None = None
    frame: str = OFFSET

    def __post_init__(self):
        s = tuple(float(v) for v in np.broadcast_to(np.asarray(self.sigma_ut, dtype=np.float64), (3,)))
        object.__setattr__(self, "sigma_ut", s)
        if not (np.all(np.isfinite(s)) and min(s) >= 0):
            raise ValueError(f"wander sigma_ut must be finite and ≥ 0, got {s}")
        if self.frame not in (OFFSET, FIELD):
            raise ValueError(f"wander frame must be {OFFSET!r} or {FIELD!r}, got {self.frame!r}")
        if self.frame == FIELD and len(set(s)) != 1:
            raise ValueError("a field wander has one sigma_ut (the field's magnitude)")
        if (self.tau_s is None) == (self.band_hz is None):
            raise ValueError("a wander component has either tau_s (OU) or band_hz (a flat band)")
        if self.tau_s is not None:
            object.__setattr__(self, "tau_s", float(self.tau_s))
            if not (np.isfinite(self.tau_s) and self.tau_s > 0):
                raise ValueError(f"wander tau_s must be positive, got {self.tau_s}")
        else:
            lo, hi = (float(v) for v in self.band_hz)
            if not (np.isfinite(hi) and 0 <= lo < hi):
                raise ValueError(f"wander band_hz must be 0 ≤ low < high, got {[lo, hi]}")
            object.__setattr__(self, "band_hz", (lo, hi))

    @property
    def variance(self) -> float:
        """Mean variance per axis (µT²)."""
        return float(np.mean(np.square(self.sigma_ut)))

    def correlation(self, lag_s) -> np.ndarray:
        """cov(w(t), w(t + lag)) / σ²."""
        d = np.abs(np.asarray(lag_s, dtype=np.float64))
        if self.tau_s is not None:
            return np.exp(-d / self.tau_s)
        lo, hi = self.band_hz
        with np.errstate(invalid="ignore", divide="ignore"):
            c = (np.sin(2 * np.pi * hi * d) - np.sin(2 * np.pi * lo * d)) / (2 * np.pi * (hi - lo) * d)
        return np.where(d == 0, 1.0, c)

    def to_dict(self) -> dict:
        d = {"sigma_ut": self.sigma_ut[0] if self.frame == FIELD else list(self.sigma_ut)}
        d.update({"tau_s": self.tau_s} if self.tau_s is not None else {"band_hz": list(self.band_hz)})
        if self.frame != OFFSET:
            d["frame"] = self.frame
        return d

    @classmethod
    def from_dict(cls, d) -> "WanderComponent":
        return cls(sigma_ut=d["sigma_ut"], tau_s=d.get("tau_s"), band_hz=d.get("band_hz"),
                   frame=d.get("frame", OFFSET))


def split(components) -> tuple[tuple, tuple]:
    """(offset components, field components)."""
    comps = tuple(components)
    return tuple(c for c in comps if c.frame == OFFSET), tuple(c for c in comps if c.frame == FIELD)


# -- drawing: random access (a function of seed and t) ----------------------------------------
def _frequencies(seed: int, index: int, c: WanderComponent) -> tuple[np.ndarray, np.ndarray]:
    """(3, K) angular frequencies and phases of one component (a function of seed and index)."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x3A9D, index])
    q = (np.arange(K_COSINES)[None, :] + rng.random((3, K_COSINES))) / K_COSINES
    if c.tau_s is not None:
        omega = np.tan(0.5 * np.pi * q) / c.tau_s  # quantiles of the Lorentzian
    else:
        lo, hi = c.band_hz
        omega = 2 * np.pi * (lo + (hi - lo) * q)
    phase = rng.uniform(0, 2 * np.pi, (3, K_COSINES))
    return omega, phase


def draw(components, seed: int, t_s, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """(offset (n, 3), field (n,)) µT at times ``t_s``: a deterministic function of (seed, t)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    out = np.zeros((len(t), 3))
    field = np.zeros(len(t))
    for j, c in enumerate(components):
        omega, phase = _frequencies(seed, j, c)
        amp = np.asarray(c.sigma_ut) * np.sqrt(2.0 / K_COSINES)
        for a in range(3 if c.frame == OFFSET else 1):
            if amp[a] == 0:
                continue
            target = out[:, a] if c.frame == OFFSET else field
            for s in range(0, len(t), chunk):
                tt = t[s : s + chunk, None]
                target[s : s + chunk] += amp[a] * np.cos(tt * omega[a] + phase[a]).sum(axis=1)
    return out, field


# -- drawing: a whole stream ---------------------------------------------------------------
def draw_path(components, rng: np.random.Generator, t_s) -> tuple[np.ndarray, np.ndarray]:
    """(offset (n, 3), field (n,)) µT along a whole stream (times ascending): the exact AR(1)
    recursion at the stream's own times per OU component, Fourier synthesis for the band
    components. Same processes as ``draw``, faster for long streams; not random access."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    out = np.zeros((len(t), 4))  # offset x, y, z and the field
    if len(t) == 0 or not components:
        return out[:, :3], out[:, 3]
    for c in components:
        if c.tau_s is not None:
            cols = [0, 1, 2] if c.frame == OFFSET else [3]
            x = _ou_path(c.tau_s, rng, t, len(cols))
            out[:, cols] += x * np.asarray(c.sigma_ut)[: len(cols)]
    bands = [c for c in components if c.band_hz is not None]
    if bands:
        out += _band_paths(bands, rng, t)
    return out[:, :3], out[:, 3]


OU_CHUNK = 600.0  # correlation times per chunk of the OU recursion (e^600 is well inside float64)


def _ou_path(tau_s: float, rng: np.random.Generator, t: np.ndarray, k: int) -> np.ndarray:
    """(n, k) unit-variance OU paths at times t: x_i = a_i x_(i-1) + √(1 − a_i²) z_i with
    a_i = exp(−(t_i − t_(i-1))/τ), the process's own transition (exact at any spacing, no grid),
    started in the stationary distribution. The linear recursion is solved in closed form,
    x_i = e^(−s_i) (a_c x_c + Σ_(j≤i) e^(s_j) b_j) with s the time since the chunk's first
    sample in units of τ, chunk by chunk so that e^s stays finite."""
    z = rng.standard_normal((len(t), k))
    a = np.exp(-np.diff(t) / tau_s)
    z[1:] *= np.sqrt(1.0 - a * a)[:, None]
    x = np.empty_like(z)
    x[0] = z[0]
    start = 1
    while start < len(t):
        stop = max(start + 1, int(np.searchsorted(t, t[start] + OU_CHUNK * tau_s, side="right")))
        s = (t[start:stop] - t[start]) / tau_s
        acc = np.cumsum(np.exp(s)[:, None] * z[start:stop], axis=0)
        acc += a[start - 1] * x[start - 1]
        x[start:stop] = np.exp(-s)[:, None] * acc
        start = stop
    return x


@lru_cache(maxsize=256)
def _fast_len(n: int) -> int:
    """The smallest 2^a 3^b 5^c ≥ n (a length numpy's FFT transforms fast). Kept per n: a
    twin's fit and draws ask for the same few lengths again and again."""
    best, p5 = 1 << max(0, int(n - 1).bit_length()), 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p = p35
            while p < n:
                p *= 2
            best = min(best, p)
            p35 *= 3
        p5 *= 5
    return best


UNIFORM = 1e-3  # times within this share of a sample period of a uniform grid are read on it
PER_PERIOD = 6.0  # grid points to the shortest period when irregular times are interpolated
TAPS = np.arange(-3, 5)  # the grid points (relative to the one before t) a reading is interpolated from
_DENOMINATOR = np.array([np.prod([xi - xj for xj in TAPS if xj != xi]) for xi in TAPS], dtype=np.float64)


def _band_paths(bands, rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """(n, 4) the band components' sum (offset x, y, z; field) by Fourier synthesis over a
    period twice the stream's span (so the periodic wrap does not correlate its ends). Uniform
    times are read on the grid of their own period (each sample a grid point: nothing
    interpolated). Irregular ones: the frequencies are those of a grid of the sample period
    divided evenly (16 points to the top band's shortest period), the values are synthesised
    on a grid of PER_PERIOD points to it and read by Lagrange interpolation through the eight
    nearest (each frequency's variance kept within 0.3 %; linear interpolation needs the 16
    points and keeps 97.5 %)."""
    n = len(t)
    span = max(float(t[-1] - t[0]), 1e-6)
    uniform = _uniform(t, span)
    if uniform:
        step = span / (n - 1)
        size = _fast_len(int(np.ceil(2.0 * span / step)) + 2)
        period = size * step
    else:
        dt = sample_interval(t) if n > 1 else span
        top = max(c.band_hz[1] for c in bands)
        fine = max(dt / max(1, int(np.ceil(16.0 * top * dt))), 4.0 * span / MAX_GRID)
        fine_size = _fast_len(int(np.ceil(2.0 * span / fine)) + 2)
        period = fine_size * fine
        size = min(fine_size, _fast_len(max(16, int(np.ceil(PER_PERIOD * top * period)))))
    spec, used = _band_spectrum(bands, rng, size, period)
    out = np.zeros((n, 4))
    grid = np.fft.irfft(spec, n=size, axis=0)  # the columns without a band stay zero
    out[:, used] = grid[:n] if uniform else _lagrange(grid, (t - t[0]) * (size / period))
    return out


_LAST_UNIFORM: list = [None]  # (times, uniform): a twin's fit and draws ask of the same times


def _uniform(t: np.ndarray, span: float) -> bool:
    """Whether the times lie on an evenly spaced grid (within UNIFORM of a period)."""
    last = _LAST_UNIFORM[0]
    if last is not None and last[0].shape == t.shape and np.array_equal(last[0], t):
        return last[1]
    n = len(t)
    uniform = bool(n > 1 and np.max(np.abs(t - np.linspace(t[0], t[-1], n))) <= UNIFORM * span / (n - 1))
    _LAST_UNIFORM[0] = (t.copy(), uniform) if n <= KEEP_READING_MAX else None
    return uniform


def _lagrange(grid: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(n, k) a periodic grid (size, k) read at fractional indices ``pos`` by the Lagrange
    polynomial through the grid points TAPS around each."""
    idx, weights = _reading(pos, len(grid))
    out = np.empty((grid.shape[1], len(pos)))
    for column, g in zip(out, np.ascontiguousarray(grid.T)):  # a column at a time: 1-d gathers
        column[:] = weights[0] * g[idx[0]]
        for i, w in zip(idx[1:], weights[1:]):
            column += w * g[i]
    return out.T


_LAST_READING: list = [None]  # (pos, size, idx, weights): a twin's draws read the same times again and again
KEEP_READING_MAX = 100_000  # times whose reading is kept (136 bytes a time: ≤ 14 MB held after the call)


def _reading(pos: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(grid index (taps, n), weight (taps, n)) of each tap of the reading at ``pos`` on a grid
    of ``size`` points: tap i's weight is Π_(j≠i) (a − x_j) / Π_(j≠i) (x_i − x_j), the numerator
    as the product of the taps before i and of those after it (no division by a − x_i: exact
    on a grid point). The last one is kept: it depends on the times alone, and every draw of a
    twin (the same components at the same times) reads the same."""
    last = _LAST_READING[0]
    if last is not None and last[1] == size and last[0].shape == pos.shape and np.array_equal(last[0], pos):
        return last[2], last[3]
    below = np.floor(pos)
    a = pos - below
    d = [a - x for x in TAPS]
    weights = np.empty((len(TAPS), len(pos)))
    before = np.ones_like(a)
    for i, di in enumerate(d):
        weights[i] = before
        before = before * di
    after = np.ones_like(a)
    for i in range(len(TAPS) - 1, -1, -1):
        weights[i] = weights[i] * after / _DENOMINATOR[i]
        after = after * d[i]
    idx = below.astype(np.int64) % size + TAPS[:, None]  # one remainder a time, then the taps' wrap
    if size > np.ptp(TAPS):
        idx[idx < 0] += size
        idx[idx >= size] -= size
    else:
        idx %= size
    _LAST_READING[0] = (pos.copy(), size, idx, weights) if len(pos) <= KEEP_READING_MAX else None
    return idx, weights


def _band_spectrum(bands, rng: np.random.Generator, size: int, period: float) -> tuple[np.ndarray, list]:
    """The random Fourier coefficients of the band components on a grid of ``size`` points over
    ``period`` seconds — each band's σ² spread evenly over the grid frequencies inside it,
    random phases — for the columns (of offset x, y, z and the field) that have any: ((size //
    2 + 1, len(used)), used). The normal deviates of all bands come from one call, in the
    order band by band, real parts then imaginary ones (the same stream as a call per part)."""
    used = sorted({i for c in bands for i in ((0, 1, 2) if c.frame == OFFSET else (3,))})
    freqs = np.arange(size // 2 + 1) * (1.0 / period)
    spec = np.zeros((len(freqs), len(used)), dtype=complex)
    edges = np.array([c.band_hz for c in bands], dtype=np.float64).reshape(-1, 2)
    firsts, stops = np.maximum(1, np.searchsorted(freqs, edges[:, 0])), np.searchsorted(freqs, edges[:, 1])
    where = []
    for c, first, stop in zip(bands, firsts.tolist(), stops.tolist()):
        if stop <= first:  # narrower than the grid resolves: its nearest frequency
            first = max(1, int(np.argmin(np.abs(freqs - 0.5 * sum(c.band_hz)))))
            stop = first + 1
        where.append((first, stop, [used.index(i) for i in ((0, 1, 2) if c.frame == OFFSET else (3,))]))
    z_all = rng.standard_normal(sum(2 * (stop - first) * len(cols) for first, stop, cols in where))
    at = 0
    for c, (first, stop, cols) in zip(bands, where):
        k, n = len(cols), (stop - first) * len(cols)
        sig = np.asarray(c.sigma_ut)[:k] / np.sqrt(stop - first)
        z = z_all[at : at + n].reshape(-1, k) - 1j * z_all[at + n : at + 2 * n].reshape(-1, k)
        at += 2 * n
        spec[first:stop, cols[0] : cols[-1] + 1] += z * sig * (size / 2.0)
    return spec, used


# -- fitting -------------------------------------------------------------------------------
def sample_interval(t_s) -> float:
    """The sensor's sample interval read from its stamps: the mean, span / (n − 1) — the number
    of samples over the time they took. Not the median: a host that stamps samples on arrival
    gets them in bursts (an HMC5883L at 77 Hz read as 2 ms apart, then a gap of up to 250 ms),
    where the median interval (3.3 ms) would put the Nyquist frequency, and so the top band,
    at 152 Hz instead of the sensor's 38 Hz; a clock that repeats its stamps has a median of 0.
    For regular stamps the two agree. 1.0 for fewer than two samples or no span."""
    t = np.asarray(t_s, dtype=np.float64)
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    return span / (len(t) - 1) if span > 0 else 1.0


def band_edges(dt_s: float, duration_s: float) -> np.ndarray:
    """Band edges from half a cycle per recording to the Nyquist frequency: log-spaced
    (BANDS_PER_DECADE to a decade) up to a quarter of Nyquist, then in equal steps of an
    eighth of it — near Nyquist the spectrum's shape (a sensor's own filter) sets how rough
    the reading is from sample to sample, which a log-spaced band would smear."""
    nyq = 0.5 / dt_s
    lo, knee = 0.5 / max(duration_s, dt_s), 0.25 * nyq
    top = knee + np.arange(1, 7) * nyq / 8.0
    if lo >= knee:
        return np.concatenate([[lo], top[top > lo]])
    k = max(1, int(np.ceil(BANDS_PER_DECADE * np.log10(knee / lo))))
    return np.concatenate([np.geomspace(lo, knee, k + 1), top])


def _binned_periodogram(x: np.ndarray, edges: np.ndarray, which: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mean periodogram ordinate in each bin between ``edges`` (Fourier indices), ordinates
    in each). ``which``: each ordinate's bin (np.digitize of its index), when already known —
    it depends on the length alone."""
    p = np.abs(np.fft.rfft(x - x.mean())) ** 2 / len(x)
    if which is None:
        which = np.digitize(np.arange(len(p)), edges)
    sums = np.bincount(which, weights=p, minlength=len(edges) + 1)
    counts = np.bincount(which, minlength=len(edges) + 1)
    return (sums / np.maximum(counts, 1))[1:-1], counts[1:-1]


def candidates(dt_s: float, duration_s: float, frames=(OFFSET, FIELD)) -> list[WanderComponent]:
    """Unit-σ band components in each frame: the columns of the fit. The offset's bands reach
    the Nyquist frequency (a sensor's own filter colours its noise there); the field's stop at
    a quarter of it (the surroundings change slowly)."""
    e = band_edges(dt_s, duration_s)
    top = {OFFSET: np.inf, FIELD: FIELD_TOP * 0.5 / dt_s}
    return [WanderComponent(1.0, band_hz=(lo, hi), frame=f) for f in frames for lo, hi in zip(e[:-1], e[1:])
            if hi <= top[f] * (1 + 1e-9)]


def fit(e: np.ndarray, u: np.ndarray, t_s: np.ndarray, project=None, seeds=(11, 12, 13),
        frames=(OFFSET, FIELD), flat_below: bool = False) -> tuple[tuple[WanderComponent, ...], float]:
    """Fit the wander components and the white radial variance to a radial residual.

    ``project`` maps a raw radial series to what is left of it after the calibration model
    is refitted (a linear projection). Each candidate is drawn with unit σ on the recording's
    own times and directions and projected the same way; its mean binned periodogram is its
    spectrum as the residual shows it (what the calibration fit absorbs is accounted for).
    The variances ≥ 0 maximise the Whittle likelihood of the residual's binned periodogram.
    ``u`` (n, 3): how an offset departure shows in the residual — the field direction, or
    Wᵀu when the offset enters the raw reading ahead of a soft-iron matrix W. Returns
    (components, white_var_ut2). Offset components are isotropic: the radial residual sees
    only u·w, so the split between axes is not observable.

    A band the projection absorbs beyond MIN_LEFT is not identifiable and gets no component;
    ``flat_below``: the lowest such bands of a frame (below every band it could fit) get the
    spectral density of its lowest fitted component instead (``continued_below``)."""
    n = len(e)
    project = project or (lambda x: x - x.mean())
    dt = sample_interval(t_s)
    cands = candidates(dt, float(t_s[-1] - t_s[0]) if n > 1 else dt, frames)
    bins = np.unique(np.round(np.geomspace(1, n // 2 + 1, 48)).astype(np.int64))
    which = np.digitize(np.arange(n // 2 + 1), bins)
    target, counts = _binned_periodogram(e, bins, which)
    columns = {}
    every = [None, *cands]
    # drawn band by band (an offset and a field candidate over the same band read their draws at
    # the same grid positions: the reading is kept between them), each with its own seed [s, j]
    for j in sorted(range(len(every)), key=lambda j: (0.0, 0.0) if every[j] is None else every[j].band_hz):
        c = every[j]
        spec, left = [], []
        for s in seeds:
            rng = np.random.default_rng([s, j])
            if c is None:
                x = rng.standard_normal(n)
            else:
                off, fld = draw_path((c,), rng, t_s)
                x = np.einsum("ij,ij->i", u, off) if c.frame == OFFSET else fld
            px = project(x)
            left.append(float(px @ px) / max(float(x @ x), 1e-300))
            spec.append(_binned_periodogram(px, bins, which)[0])
        columns[j] = (np.mean(spec, axis=0), np.mean(left))
    cols, kept = [], []
    for j, c in enumerate(every):
        if c is None or columns[j][1] >= MIN_LEFT:
            cols.append(columns[j][0])
            kept.append(c)
    cands = kept[1:]
    design = np.column_stack(cols)
    ok = (counts > 0) & (design[:, 0] > 0) & (target > 0)
    if not ok.any():  # a residual with no power at all (exactly constant): no wander, no noise
        return (), 0.0
    white, var = _white_floor(design[ok], target[ok], counts[ok], bins[:-1][ok] >= n // 8)
    keep = _local_share(var, white, cands, dt) > MIN_SHARE
    comps = tuple(WanderComponent(np.sqrt(v), band_hz=c.band_hz, frame=c.frame) for v, c, k in zip(var, cands, keep) if k)
    if flat_below:
        comps += continued_below(comps, [c for c in every[1:] if c not in cands])
    return comps, white


def continued_below(comps: tuple, hidden: list) -> tuple[WanderComponent, ...]:
    """Components for the bands ``hidden`` (candidates the projection absorbs, so the residual
    cannot show their power) that lie below every fitted band of their frame: the spectrum
    continued flat at its lowest fitted band's density. A wander's spectrum does not fall
    toward the lowest frequencies (a random walk, 1/f noise, an OU process are all flat or
    rising there), so this is the least the residual's own spectrum implies; dropped, a wander
    longer than the recording — a slow trend the refit takes up as a time drift or a slow
    channel — would never be drawn."""
    out = []
    for frame in {c.frame for c in comps}:
        lowest = min((c for c in comps if c.frame == frame), key=lambda c: c.band_hz[0])
        density = lowest.variance / (lowest.band_hz[1] - lowest.band_hz[0])
        out += [WanderComponent(np.sqrt(density * (c.band_hz[1] - c.band_hz[0])), band_hz=c.band_hz, frame=frame)
                for c in hidden if c.frame == frame and c.band_hz[1] <= lowest.band_hz[0] * (1 + 1e-9)]
    return tuple(sorted(out, key=lambda c: (c.frame, c.band_hz)))


def _bands_of(cands) -> tuple[np.ndarray, list, np.ndarray]:
    """(each candidate's width in Hz, the distinct bands, each candidate's index among them)."""
    width = np.array([c.band_hz[1] - c.band_hz[0] for c in cands])
    keys = sorted({c.band_hz for c in cands})
    return width, keys, np.array([keys.index(c.band_hz) for c in cands])


def _local_share(var: np.ndarray, white: float, cands, dt_s: float) -> np.ndarray:
    """Each component's share of the fitted spectral density within its own band (all frames'
    bands over the same frequencies, and the white floor). A share of the total variance would
    drop every band above a steep red spectrum's low end, though those bands alone set how
    smooth the reading is from second to second (lag-1, the spectrum's slope)."""
    if not len(var):
        return np.zeros(0)
    width, keys, which = _bands_of(cands)
    dens = var / width
    local = np.bincount(which, weights=dens, minlength=len(keys))[which] + white * 2.0 * dt_s
    return np.where(local > 0, dens / np.maximum(local, 1e-300), 0.0)


def _white_floor(design: np.ndarray, target: np.ndarray, counts: np.ndarray, high: np.ndarray) -> tuple[float, np.ndarray]:
    """(white variance, band variances): the Whittle fit, with the spectrum's flat floor given
    to the white noise. Bands that reach the Nyquist frequency and white noise make nearly the
    same spectrum, so the fit may split them either way. The floor is the lowest level of the
    fitted spectrum, in units of the white column, over the periodogram bins above a quarter
    of the Nyquist frequency (``high``: where a wander has died away and many ordinates pin the
    level); read in the periodogram's own frequencies, it holds for irregular sampling, where a
    band's power spreads over all of them. The bands are then fitted to what stands above it."""
    coef = _whittle(design, target, counts)
    if not high.any():
        return float(coef[0]), coef[1:]
    floor = float(np.min((design[high] @ coef) / design[high, 0]))
    if floor <= coef[0]:
        return float(coef[0]), coef[1:]
    return floor, _whittle(design[:, 1:], target, counts, fixed=floor * design[:, 0])


def _whittle(design: np.ndarray, target: np.ndarray, counts: np.ndarray, rounds: int = 30,
             fixed: np.ndarray | float = 0.0) -> np.ndarray:
    """Non-negative weights w maximising the Whittle likelihood Σ_b m_b (log S_b + Ī_b / S_b),
    S = fixed + design @ w: Fisher scoring (iteratively reweighted non-negative least squares,
    weights √m_b / S_b), started from the fit in relative error; each round's active set starts
    at the last round's positive weights (the rounds' problems differ only in their weights)."""
    w = nnls(design * (np.sqrt(counts) / target)[:, None], np.sqrt(counts) * (target - fixed) / target)[0]
    for _ in range(rounds):
        spec = np.maximum(fixed + design @ w, 1e-12 * float(np.max(target)))
        wt = np.sqrt(counts) / spec
        new = nnls(design * wt[:, None], (target - fixed) * wt, start=w > 0)[0]
        if np.allclose(new, w, rtol=1e-6, atol=1e-12 * max(float(new.max()), 1e-300)):
            return new
        w = new
    return w
