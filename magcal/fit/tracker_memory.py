"""The tracker's memory: a coverage-balanced buffer of samples, and the wander it shows.

``CellBuffer``: the sphere of directions (about a centre, the current offset estimate) is cut
into equal-area cells (``coverage.cell_index``); each cell keeps at most ``per_cell`` samples
with their times. A full cell gives up the older of its two samples closest in time, so each
cell keeps samples spread over the time it has been visited — the history of every
direction, thinned, not only its last pass — and memory is ``cells × per_cell`` samples however
long the stream. When the calibration wanders (ρ = q/s² > 0, from ``Wander``) the times are
read on the information clock −log(1 + ρ·age), on which a sample's weight falls evenly, so the
kept samples thin out with age as fast as their weight does; samples from before a sudden
change (an *epoch* ago, ``Tracker``) go before any other. Every sample also records which visit to its cell it came in (a visit ends when
a sample goes to another cell), which ``Wander`` uses.

``Wander``: how fast the calibration wanders, from the data (see its docstring).
"""

from __future__ import annotations

import math

import numpy as np

from .coverage import cell_index

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


class Wander:
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
    def from_state(cls, d: dict) -> "Wander":
        w = cls()
        w.n = int(d["n"])
        w.sum_q = np.asarray(d["sum_q"], dtype=np.float64).reshape(w.sum_q.shape)
        w.sum_log = np.asarray(d["sum_log"], dtype=np.float64).reshape(w.sum_log.shape)
        return w


class CellBuffer:
    """At most ``per_cell`` samples per equal-area direction cell (see the module docstring)."""

    _ARRAYS = ("m", "t", "valid", "seq", "visit_of", "epoch_of")

    def __init__(self, bands: int, sectors: int, per_cell: int, min_share: float):
        self.bands, self.sectors, self.per_cell, self.min_share = bands, sectors, per_cell, min_share
        cells = bands * sectors
        cap = cells * per_cell
        self.m = np.zeros((cap, 3))
        self.t = np.zeros(cap)
        self.valid = np.zeros(cap, bool)
        self.seq = np.zeros(cap, np.int64)  # order of arrival (1, 2, …)
        self.visit_of = np.zeros(cap, np.int64)
        self.epoch_of = np.zeros(cap, np.int64)  # sudden changes seen before the sample came
        self.epoch = 0
        self.count = np.zeros(cells, np.int64)
        self.visits = np.zeros(cells, np.int64)
        self.seq_count = 0
        self.last_cell = -1
        self.centre: tuple[float, float, float] | None = None
        self.rho_per_s = 0.0  # how fast old samples lose weight (q/s², set by the tracker)

    def cell(self, x: float, y: float, z: float) -> int:
        cx, cy, cz = self.centre
        dx, dy, dz = x - cx, y - cy, z - cz
        norm = math.sqrt(dx * dx + dy * dy + dz * dz) or 1.0
        band = min(int((dz / norm + 1.0) * 0.5 * self.bands), self.bands - 1)
        sector = min(int((math.atan2(dy, dx) + math.pi) / (2.0 * math.pi) * self.sectors), self.sectors - 1)
        return band * self.sectors + sector

    def add(self, x: float, y: float, z: float, t_s: float) -> None:
        """File one sample (its direction about ``centre``, which must be set)."""
        k = self.per_cell
        cell = self.cell(x, y, z)
        lo = cell * k
        n = int(self.count[cell])
        if n < k:
            slot = lo + n
            self.count[cell] = n + 1
        elif int(self.epoch_of[lo:lo + k].min()) < self.epoch:  # a sample from before a sudden
            ep = self.epoch_of[lo:lo + k]                       # change goes first, oldest first
            old = np.flatnonzero(ep == ep.min())
            slot = lo + int(old[np.argmin(self.t[lo:lo + k][old])])
        else:  # the older of the two samples closest on the information clock
            rho = self.rho_per_s
            if rho > 0:
                tt = [-math.log1p(rho * max(t_s - a, 0.0)) for a in self.t[lo:lo + k].tolist()]
            else:
                tt = self.t[lo:lo + k].tolist()
            order = sorted(range(k), key=tt.__getitem__)
            gaps = [tt[order[i + 1]] - tt[order[i]] for i in range(k - 1)]
            slot = lo + order[gaps.index(min(gaps))]
        self.m[slot] = (x, y, z)
        self.t[slot] = t_s
        self.valid[slot] = True
        self.seq_count += 1
        self.seq[slot] = self.seq_count
        if cell != self.last_cell:
            self.visits[cell] += 1
            self.last_cell = cell
        self.visit_of[slot] = self.visits[cell]
        self.epoch_of[slot] = self.epoch

    def rebin(self, centre, force: bool = False) -> bool:
        """Re-file the kept samples about a new centre (per cell the newest kept). Refused
        (unless forced) when fewer cells would be occupied than now: a centre that crowds the
        samples into few cells would starve the fit of the directions it needs to recover."""
        centre = np.asarray(centre, dtype=np.float64).reshape(3)
        idx = np.flatnonzero(self.valid)
        cells = cell_index(self.m[idx] - centre, self.bands, self.sectors)
        if not force and len(np.unique(cells)) < self.occupied():
            return False
        k = self.per_cell
        order = np.lexsort((-self.t[idx], cells))  # by cell, newest first
        cells, src = cells[order], idx[order]
        rank = np.arange(len(cells)) - np.searchsorted(cells, cells, side="left")
        keep = rank < k
        src, cells, rank = src[keep], cells[keep], rank[keep]
        moved = {a: getattr(self, a)[src].copy() for a in self._ARRAYS}
        self.valid[:] = False
        slots = cells * k + rank
        for a, v in moved.items():
            getattr(self, a)[slots] = v
        self.count[:] = np.bincount(cells, minlength=len(self.count))
        self.centre = tuple(float(v) for v in centre)
        return True

    def samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(slots, m (N, 3), t (N,), cell weight (N,), mean 1): each occupied cell carries the
        same total weight, a cell's count floored at ``min_share`` of a full cell."""
        idx = np.flatnonzero(self.valid)
        cnt = self.count[idx // self.per_cell]
        w = 1.0 / np.maximum(cnt, max(self.min_share * self.per_cell, 1e-12))
        return idx, self.m[idx], self.t[idx], (w / w.mean() if len(w) else w)

    def occupied(self) -> int:
        return int(np.count_nonzero(self.count))

    def pairs(self, idx: np.ndarray, e: np.ndarray, since: int, offset_ut) -> tuple:
        """For each sample that arrived after ``since`` (a ``seq``), the nearest older sample in
        its own cell since the last sudden change: (e_new − e_old, angle δ rad, another visit?,
        Δt s). ``idx``, ``e``: the slots in memory and their residuals (as ``samples`` orders them)."""
        k = self.per_cell
        pos = np.full(len(self.valid), -1)
        pos[idx] = np.arange(len(idx))
        new = idx[self.seq[idx] > since]
        if len(new) == 0:
            return (np.zeros(0),) * 4
        cand = (new // k * k)[:, None] + np.arange(k)[None, :]
        ok = self.valid[cand] & (self.seq[cand] <= since) & (self.epoch_of[cand] == self.epoch)
        u = self.m - np.asarray(offset_ut)
        u /= np.maximum(np.linalg.norm(u, axis=1), 1e-300)[:, None]
        cos = np.where(ok, np.einsum("ij,ikj->ik", u[new], u[cand]), -np.inf)
        has = ok.any(axis=1)
        old = cand[np.arange(len(new)), np.argmax(cos, axis=1)][has]
        new = new[has]
        c = np.clip(np.einsum("ij,ij->i", u[new], u[old]), -1.0, 1.0)
        return (e[pos[new]] - e[pos[old]], np.arccos(c), self.visit_of[new] != self.visit_of[old],
                self.t[new] - self.t[old])

    def to_state(self) -> dict:
        idx = np.flatnonzero(self.valid)
        return {
            "slots": idx.tolist(), "m": self.m[idx].tolist(), "t": self.t[idx].tolist(),
            "seq": self.seq[idx].tolist(), "visit_of": self.visit_of[idx].tolist(),
            "epoch_of": self.epoch_of[idx].tolist(), "epoch": self.epoch,
            "visits": self.visits.tolist(), "seq_count": self.seq_count, "last_cell": self.last_cell,
            "centre": None if self.centre is None else list(self.centre), "rho_per_s": self.rho_per_s,
        }

    def load_state(self, d: dict) -> None:
        idx = np.asarray(d["slots"], dtype=np.int64)
        if len(idx) and (idx.min() < 0 or idx.max() >= len(self.valid)):
            raise ValueError("tracker state does not fit this buffer's size")
        self.m[idx] = np.asarray(d["m"], dtype=np.float64).reshape(-1, 3)
        self.t[idx] = np.asarray(d["t"], dtype=np.float64)
        self.seq[idx] = np.asarray(d["seq"], dtype=np.int64)
        self.visit_of[idx] = np.asarray(d["visit_of"], dtype=np.int64)
        self.epoch_of[idx] = np.asarray(d["epoch_of"], dtype=np.int64)
        self.epoch = int(d["epoch"])
        self.valid[idx] = True
        self.count[:] = np.bincount(idx // self.per_cell, minlength=len(self.count))
        self.visits[:] = np.asarray(d["visits"], dtype=np.int64)
        self.seq_count, self.last_cell = int(d["seq_count"]), int(d["last_cell"])
        self.centre = None if d["centre"] is None else tuple(float(v) for v in d["centre"])
        self.rho_per_s = float(d["rho_per_s"])
