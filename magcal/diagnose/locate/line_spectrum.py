"""The line search's statistic on a frequency grid (``magcal.diagnose.locate.lines``).

The radial residual times each direction component, ``r·u_k``, is gridded on a clock fine enough
for the highest frequency scanned (uneven timestamps rounded to it; samples that share a cell
add), transformed, and whitened by the direction covariance, so that on white noise each
frequency's explained square is σ²·χ² with two degrees of freedom per determined direction. Each
frequency is judged against the local level of that statistic: the running median over
``HALF_WINDOW`` independent bins each side, ``GAP`` bins each side left out. The same statistic
of one logged channel alone (one column) is that channel's own periodogram.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from ...fit import tails

ALPHA = 0.002  # chance of any false line over all frequencies scanned, per search
PAD = 4  # frequency grid oversampling
HALF_WINDOW = 40  # independent bins each side that set the local level
GAP = 3  # independent bins each side of the candidate left out of its local level
GRID_TRIALS = 2.0  # the maximum over the oversampled grid, counted as this many tries per independent bin
LEVEL_EFFICIENCY = 0.6  # a median of χ² values is worth this share of their number in degrees of freedom
MIN_CYCLES = 8.0  # lowest frequency scanned: this many cycles over the recording
TOP_NYQUIST = 1.0  # highest frequency scanned, as a share of the Nyquist frequency (mains at half the clock lands on it)
MAX_PHASE_RAD = 0.3  # gridding error allowed at the highest frequency scanned


@dataclass(frozen=True)
class Spectrum:
    """The whitened line statistic on a frequency grid, and its local level."""

    freq_hz: np.ndarray
    stat: np.ndarray  # explained square of the six columns / local σ², per frequency
    level: np.ndarray  # local σ² (µT²) of the radial residual near each frequency
    dof: int
    n_independent: float

    @property
    def threshold(self) -> float:
        """The statistic a line must exceed: ALPHA over every frequency scanned. On white noise
        the statistic is χ²(dof) over a level known to ``LEVEL_DOF`` degrees of freedom, so
        stat/dof is F(dof, LEVEL_DOF); the oversampled grid's maximum counts GRID_TRIALS tries
        per independent bin."""
        trials = max(self.n_independent, 1.0) * GRID_TRIALS
        return float(self.dof * tails.f_isf(ALPHA / trials, self.dof, LEVEL_EFFICIENCY * self.dof * 2 * (HALF_WINDOW - GAP)))


def sample_interval_s(t_s: np.ndarray) -> float:
    """The median interval between samples (s); where the clock repeats its stamps (median
    interval 0), the mean one. ValueError when time runs backwards or does not advance."""
    dt = np.diff(t_s)
    if len(dt) == 0 or not np.all(np.isfinite(t_s)):
        raise ValueError("t_s must hold finite times of at least two samples")
    if np.any(dt < 0) or t_s[-1] <= t_s[0]:
        raise ValueError("t_s must be in time order and advance over the recording")
    d = float(np.median(dt))
    return d if d > 0 else float(t_s[-1] - t_s[0]) / len(dt)


def grid_of(t_s: np.ndarray, dt_s: float, f_max_hz: float) -> tuple[np.ndarray, float]:
    """(grid cell of each sample, cell width): the coarsest of dt, dt/2 … dt/8 whose rounding
    of the timestamps costs at most MAX_PHASE_RAD at ``f_max_hz``."""
    rel = t_s - t_s[0]
    for q in (1, 2, 4, 8):
        step = dt_s / q
        idx = np.round(rel / step).astype(np.int64)
        if 2 * np.pi * f_max_hz * np.max(np.abs(rel - idx * step)) <= MAX_PHASE_RAD:
            break
    return idx, step


def spectrum(t_s: np.ndarray, r_ut: np.ndarray, u: np.ndarray) -> Spectrum | None:
    """The line statistic over every scanned frequency; None when the span holds too few cycles."""
    dt = sample_interval_s(t_s)
    span = float(t_s[-1] - t_s[0])
    f_lo, f_hi = MIN_CYCLES / span, TOP_NYQUIST * 0.5 / dt
    if f_lo >= f_hi:
        return None
    idx, step = grid_of(t_s, dt, f_hi)
    size = sfft.next_fast_len(int(PAD * (idx[-1] + 1)))
    x = np.zeros((3, size))
    for k in range(3):
        np.add.at(x[k], idx, r_ut * u[:, k])
    z = sfft.rfft(x, axis=1)
    freq = np.arange(z.shape[1]) / (size * step)
    band = (freq >= 1.0 / span) & (freq <= f_hi)  # the level below f_lo is read, not scanned
    minv, rank = _direction_inverse(u)
    ess = 2.0 / len(t_s) * np.real(np.einsum("kf,kj,jf->f", np.conj(z[:, band]), minv, z[:, band]))
    dof = 2 * rank
    level = local_level(ess, dof)
    keep = freq[band] >= f_lo
    return Spectrum(freq[band][keep], ess[keep] / level[keep], level[keep], dof, keep.sum() / (size * step / span))


def _direction_inverse(u: np.ndarray) -> tuple[np.ndarray, int]:
    """The pseudo-inverse of the mean direction outer product and its rank."""
    m = u.T @ u / len(u)
    w, v = np.linalg.eigh(m)
    ok = w > 1e-3 * w.max()
    return (v[:, ok] / w[ok]) @ v[:, ok].T, int(ok.sum())


def local_level(ess: np.ndarray, dof: int) -> np.ndarray:
    """σ² near each frequency: the running median of the explained square over HALF_WINDOW
    independent bins each side (GAP bins each side of the centre left out), as σ²."""
    coarse = ess[::PAD]
    foot = np.ones(2 * HALF_WINDOW + 1, bool)
    foot[HALF_WINDOW - GAP : HALF_WINDOW + GAP + 1] = False
    med = ndimage.median_filter(coarse, footprint=foot, mode="mirror")
    med = np.maximum(med, np.finfo(float).tiny)
    fine = np.exp(np.interp(np.arange(len(ess)) / PAD, np.arange(len(coarse)), np.log(med)))
    return fine / tails.chi2_isf(0.5, dof)
