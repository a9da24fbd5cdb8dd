"""The tracker's memory, read: how fast the calibration wanders, and the samples' weights.

The samples themselves are kept by the one sample buffer, ``cell_buffer.CellBuffer`` (the
tracker's with ``WhenFull.THIN``: time-spread thinning on the information clock this module's
wander rate sets).

``WanderRate``: how fast the calibration wanders, from the data (see its docstring), comparing each
new sample with the nearest older one the buffer keeps in its own cell (``CellBuffer.pairs``).
``sample_weights``: cell balance × age × Huber, the weights of the tracker's solve.
"""

from __future__ import annotations

import numpy as np

WANDER_CHI2 = 10.83  # χ²₁ at 0.1 %: wander is assumed only where the likelihood shows it
RHO_GRID_PER_S = np.concatenate([[0.0], np.logspace(-6, 1, 15)])
GAMMA_GRID_PER_RAD2 = np.concatenate([[0.0], np.logspace(0, 6, 7)])
KAPPA_GRID = np.concatenate([[0.0], np.logspace(-2, 2, 13)])


def robust_scale(e: np.ndarray) -> float:
    """1.4826 × the median absolute deviation (σ of Gaussian residuals, spikes ignored)."""
    med = float(np.median(e))
    return max(1.4826 * float(np.median(np.abs(e - med))), 1e-9)


def sample_weights(e, age_s, wc, q: float, steps_ut2, huber_k: float) -> tuple[np.ndarray, float]:
    """(w with mean 1, s²): cell balance ``wc`` × age × Huber, from the radial residuals ``e``
    under the calibration in force. s is the residual scale of a fresh sample: the robust
    scale of e/√(1 + q·a/s²), solved by fixed point, since old samples are expected to sit further
    off; a sample of age a counts 1/(1 + q·a/s² + its squared steps since, ``steps_ut2``, over s²)."""
    scale = robust_scale(e)
    stretch = np.ones(len(e))
    for _ in range(3 if q > 0 else 0):
        stretch = np.sqrt(1.0 + (q / (scale * scale)) * age_s)
        scale = robust_scale(e / stretch)
    s2 = scale * scale
    cap = huber_k * scale * stretch
    w = wc * np.minimum(1.0, cap / np.maximum(np.abs(e), 1e-300)) / (1.0 + (q / s2) * age_s + steps_ut2 / s2)
    return w / w.mean(), s2


class WanderRate:
    """q (µT²/s), the rate at which the calibration wanders, by maximum likelihood.

    Each new sample is compared with the nearest older sample kept in its own direction cell,
    both under the calibration in force: d = e_new − e_old (radial residuals). Besides noise,
    three things make them differ: the shape error the ellipsoid leaves, which changes with how
    far apart they point (δ); an error shared within one visit to the cell but not across visits
    (a motion-dependent error that does not last, and must not be followed); and the wander that
    lasts, growing with the time Δt between them:

        d ~ N(0, s²·(2 + γ·δ² + κ·[another visit] + ρ·Δt)),   q = ρ·s²

    The likelihood is kept as running sums on a (γ, κ, ρ) grid, so evidence accumulates over the
    stream in O(grid) per sample; q is zero unless the likelihood-ratio test against ρ = 0
    passes at 0.1 %."""

    def __init__(self):
        shape = (len(GAMMA_GRID_PER_RAD2), len(KAPPA_GRID), len(RHO_GRID_PER_S))
        self.n = 0
        self.sum_q = np.zeros(shape)  # Σ d² / v
        self.sum_log = np.zeros(shape)  # Σ log v

    def add(self, d, delta_rad, other_visit, dt_s) -> None:
        d = np.asarray(d, dtype=np.float64).reshape(-1)
        if len(d) == 0:
            return
        g = GAMMA_GRID_PER_RAD2[None, :, None, None] * (np.asarray(delta_rad, np.float64) ** 2)[:, None, None, None]
        k = KAPPA_GRID[None, None, :, None] * np.asarray(other_visit, np.float64)[:, None, None, None]
        r = RHO_GRID_PER_S[None, None, None, :] * np.maximum(np.asarray(dt_s, np.float64), 0.0)[:, None, None, None]
        v = 2.0 + g + k + r
        self.sum_q += np.tensordot(d * d, 1.0 / v, axes=1)
        self.sum_log += np.log(v).sum(axis=0)
        self.n += len(d)

    def _best(self) -> tuple[float, int, int, int]:
        """(s², γ index, κ index, ρ index) at the maximum; ρ = 0 unless the test passes."""
        s2 = np.maximum(self.sum_q / self.n, 1e-300)
        ll = -0.5 * (self.n * np.log(s2) + self.sum_log)
        best = np.unravel_index(int(np.argmax(ll)), ll.shape)
        g0, k0 = np.unravel_index(int(np.argmax(ll[..., 0])), ll.shape[:2])
        if 2.0 * (ll[best] - ll[g0, k0, 0]) < WANDER_CHI2:
            return float(s2[g0, k0, 0]), int(g0), int(k0), 0  # no lasting wander the data can show
        return float(s2[best]), int(best[0]), int(best[1]), int(best[2])

    def solve(self) -> tuple[float, float]:
        """(s², q); (nan, 0) before any evidence."""
        if self.n == 0:
            return float("nan"), 0.0
        s2, _, _, r = self._best()
        return s2, float(RHO_GRID_PER_S[r] * s2)

    def variance(self, delta_rad, other_visit, dt_s) -> np.ndarray | None:
        """What the fitted model expects of d² for these pairs (None before any evidence)."""
        if self.n == 0:
            return None
        s2, g, k, r = self._best()
        return s2 * (2.0 + GAMMA_GRID_PER_RAD2[g] * np.asarray(delta_rad) ** 2
                     + KAPPA_GRID[k] * np.asarray(other_visit, np.float64) + RHO_GRID_PER_S[r] * np.asarray(dt_s))

    def to_state(self) -> dict:
        return {"n": self.n, "sum_q": self.sum_q.tolist(), "sum_log": self.sum_log.tolist()}

    @classmethod
    def from_state(cls, d: dict) -> "WanderRate":
        w = cls()
        w.n = int(d["n"])
        w.sum_q = np.asarray(d["sum_q"], dtype=np.float64).reshape(w.sum_q.shape)
        w.sum_log = np.asarray(d["sum_log"], dtype=np.float64).reshape(w.sum_log.shape)
        return w
