"""The offset wander: a sum of Ornstein–Uhlenbeck processes, drawn and fitted.

Real residuals are not white (docs/sensor-model.md): the offset moves slowly — temperature
the sensor does not report, a magnetised part relaxing, the hand's own iron. The model is a sum
of independent components, each an Ornstein–Uhlenbeck process per sensor axis with stationary
standard deviation ``sigma_ut`` and correlation time ``tau_s``::

    cov(w(t), w(t + Δ)) = Σ_k σ_k² exp(−|Δ| / τ_k)

A component with τ far beyond the recording is a random walk there; one with τ near the
sample period is coloured noise (a sensor's own low-pass filter).

Drawing, two samplers of the one process: ``draw`` synthesises each component from its
spectrum as a sum of cosines whose angular frequencies are stratified quantiles of the
Lorentzian (ω = tan(π q / 2) / τ), random phases, equal amplitudes σ·√(2/K) — the covariance is
exactly the OU covariance in expectation, and every value is a function of (seed, t) alone, so
the simulated board can be sampled at any time, in any order, and reproduced. ``draw_path``
runs the exact AR(1) recursion of each component along a whole stream (a twin of a recording,
whose times are known at once), which is faster for long streams.

Fitting (``fit``): the radial residual e_i = |h_i| − r of a recording sees the offset wander
through the field direction, e_i ≈ u_i · w(t_i) + white noise, so its autocovariance at lag L is

    c(L) ≈ s_white δ_L + Σ_k σ_k² exp(−Δt_L / τ_k) · g(L),    g(L) = mean(u_i · u_{i+L})

with g measured from the recording's own directions. Non-negative least squares over a fixed
grid of τ (a fitted spectrum) gives the σ_k; components that carry little variance are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal
from scipy.optimize import minimize, nnls

K_COSINES = 48  # cosines per component and axis
MIN_SHARE = 0.02  # a component carrying less than this share of the fitted variance is dropped


@dataclass(frozen=True)
class Wander:
    """One OU component of the offset: stationary σ per sensor axis (µT), correlation time (s)."""

    sigma_ut: tuple
    tau_s: float

    def __post_init__(self):
        s = tuple(float(v) for v in np.broadcast_to(np.asarray(self.sigma_ut, dtype=np.float64), (3,)))
        object.__setattr__(self, "sigma_ut", s)
        object.__setattr__(self, "tau_s", float(self.tau_s))
        if not (np.all(np.isfinite(s)) and min(s) >= 0):
            raise ValueError(f"wander sigma_ut must be finite and ≥ 0, got {s}")
        if not (np.isfinite(self.tau_s) and self.tau_s > 0):
            raise ValueError(f"wander tau_s must be positive, got {self.tau_s}")

    def to_dict(self) -> dict:
        return {"sigma_ut": list(self.sigma_ut), "tau_s": self.tau_s}

    @classmethod
    def from_dict(cls, d) -> "Wander":
        return cls(sigma_ut=d["sigma_ut"], tau_s=d["tau_s"])


def _spectrum(seed: int, index: int, tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(3, K) angular frequencies and phases of one component (a function of seed and index)."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x3A9D, index])
    q = (np.arange(K_COSINES)[None, :] + rng.random((3, K_COSINES))) / K_COSINES
    omega = np.tan(0.5 * np.pi * q) / tau_s
    phase = rng.uniform(0, 2 * np.pi, (3, K_COSINES))
    return omega, phase


def draw(components, seed: int, t_s, chunk: int = 8192) -> np.ndarray:
    """The wander (n, 3) µT at times ``t_s``: a deterministic function of (seed, t)."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    out = np.zeros((len(t), 3))
    for j, c in enumerate(components):
        omega, phase = _spectrum(seed, j, c.tau_s)
        amp = np.asarray(c.sigma_ut) * np.sqrt(2.0 / K_COSINES)
        for a in range(3):
            if amp[a] == 0:
                continue
            for s in range(0, len(t), chunk):
                tt = t[s : s + chunk, None]
                out[s : s + chunk, a] += amp[a] * np.cos(tt * omega[a] + phase[a]).sum(axis=1)
    return out


def draw_path(components, rng: np.random.Generator, t_s) -> np.ndarray:
    """The wander (n, 3) µT along a whole stream at once (times ascending): each component an
    exact AR(1) recursion on a uniform grid fine enough for its τ, read at ``t_s`` by linear
    interpolation. Same process as ``draw``, faster for long streams; not random access."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    out = np.zeros((len(t), 3))
    if len(t) == 0 or not components:
        return out
    span = float(t[-1] - t[0])
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    for c in components:
        step = max(min(dt, c.tau_s / 4.0), span / 2_000_000, 1e-9)
        n = int(np.ceil(span / step)) + 2
        a = np.exp(-step / c.tau_s)
        z = rng.standard_normal((n, 3)) * np.sqrt(1.0 - a * a)
        z[0] = rng.standard_normal(3)  # start in the stationary distribution
        x = signal.lfilter([1.0], [1.0, -a], z, axis=0)
        grid = t[0] + step * np.arange(n)
        for k in range(3):
            out[:, k] += c.sigma_ut[k] * np.interp(t, grid, x[:, k])
    return out


def lag_grid(n: int, most: int = 28) -> np.ndarray:
    """Lags 0, 1, 2, … roughly log-spaced up to n/4."""
    top = max(2, n // 4)
    lags = np.unique(np.round(np.geomspace(1, top, most)).astype(np.int64))
    return np.concatenate([[0], lags])


def autocovariance(e: np.ndarray, lags: np.ndarray) -> np.ndarray:
    e = e - e.mean()
    n = len(e)
    return np.array([float(e[: n - k] @ e[k:]) / (n - k) for k in lags])


def direction_overlap(u: np.ndarray, lags: np.ndarray) -> np.ndarray:
    n = len(u)
    return np.array([float(np.einsum("ij,ij->", u[: n - k], u[k:])) / (n - k) for k in lags])


def tau_grid(dt_s: float, duration_s: float) -> np.ndarray:
    """Correlation times from two sample periods to three recording lengths."""
    lo, hi = 2.0 * dt_s, 3.0 * duration_s
    return np.geomspace(lo, max(hi, 4 * lo), 14)


def _binned_periodogram(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    p = np.abs(np.fft.rfft(x - x.mean())) ** 2 / len(x)
    k = np.arange(len(p))
    sums = np.bincount(np.digitize(k, edges), weights=p, minlength=len(edges) + 1)
    counts = np.bincount(np.digitize(k, edges), minlength=len(edges) + 1)
    return (sums / np.maximum(counts, 1))[1:-1], counts[1:-1]


def fit(e: np.ndarray, u: np.ndarray, t_s: np.ndarray, project=None, seeds=(11, 12, 13)) -> tuple[tuple[Wander, ...], float]:
    """Fit the wander components and the white radial variance to a radial residual.

    ``project`` maps a raw radial series to what is left of it after the calibration model
    is refitted (a linear projection). Each candidate component (a grid of τ) is drawn with unit
    σ on the recording's own times and directions and projected the same way; its mean
    periodogram, in log-spaced frequency bands, is that component's spectrum as the residual
    shows it (simulated moments: what the calibration fit absorbs is accounted for). The
    variances σ_k² ≥ 0 and the white variance minimise the Whittle likelihood of the residual's
    banded periodogram. Returns (components, white_var_ut2). The components are isotropic:
    the radial residual sees only u·w, so the split between axes is not observable."""
    n = len(e)
    project = project or (lambda x: x - x.mean())
    dt = float(np.median(np.diff(t_s))) if n > 1 else 1.0
    taus = tau_grid(dt, float(t_s[-1] - t_s[0]) if n > 1 else dt)
    edges = np.unique(np.round(np.geomspace(1, n // 2 + 1, 40)).astype(np.int64))
    target, counts = _binned_periodogram(e, edges)
    cols = []
    for j, tau in enumerate([None, *taus]):
        spec = []
        for s in seeds:
            rng = np.random.default_rng([s, j])
            x = rng.standard_normal(n) if tau is None else np.einsum("ij,ij->i", u, draw_path((Wander(1.0, tau),), rng, t_s))
            spec.append(_binned_periodogram(project(x), edges)[0])
        cols.append(np.mean(spec, axis=0))
    design = np.column_stack(cols)
    ok = (counts > 0) & np.all(design > 0, axis=1) & (target > 0)
    coef = _whittle(design[ok], target[ok], counts[ok])
    white, var = float(coef[0]), coef[1:]
    total = var.sum()
    comps = tuple(Wander(sigma_ut=np.sqrt(v), tau_s=tau) for v, tau in zip(var, taus)
                  if total > 0 and v > MIN_SHARE * total)
    return comps, white


def _whittle(design: np.ndarray, target: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Non-negative weights w minimising Σ_b m_b (log S_b + Ī_b / S_b), S = design @ w."""
    start, _ = nnls(design / target[:, None], np.ones(len(target)))
    start = np.maximum(start, 1e-6 * max(start.max(), 1e-12))

    def cost(z):
        w = np.exp(z)
        spec = design @ w
        r = target / spec
        grad = design.T @ (counts * (1.0 - r) / spec) * w
        return float(np.sum(counts * (np.log(spec) + r))), grad

    white = np.full(len(start), 1e-6 * max(start.max(), 1e-12))
    white[0] = float(np.mean(target / design[:, 0]))
    best = None
    for z0 in (np.log(start), np.log(white)):  # two starts: the linear fit, and white noise alone
        res = minimize(cost, z0, jac=True, method="L-BFGS-B", bounds=[(-60.0, 60.0)] * len(start))
        if best is None or res.fun < best.fun:
            best = res
    return np.exp(best.x)


def scaled(components, factors) -> tuple[Wander, ...]:
    """The components with each σ² multiplied by the matching factor."""
    return tuple(Wander(sigma_ut=np.asarray(c.sigma_ut) * np.sqrt(max(f, 0.0)), tau_s=c.tau_s)
                 for c, f in zip(components, factors))
