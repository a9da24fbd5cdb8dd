"""The sample buffer: at most ``per_cell`` samples in each equal-area cell of directions.

The sphere of directions about a centre (the current offset estimate) is cut into equal-area
cells (``coverage.cell_index``), and each cell keeps at most ``per_cell`` samples with their
times, so hovering in one pose cannot crowd out the rest and memory is ``cells × per_cell``
samples however long the stream. This one buffer serves both users; what differs is what a
full cell gives up to a newcomer (``WhenFull``):

* ``REFUSE`` — the newcomer: first come, first kept. The session's final maximum-likelihood
  fit (``logic.session``) takes the first well-spread samples of a calibration dance.
* ``THIN`` — the older of its two samples closest in time, so each cell keeps samples spread
  over the time it has been visited — the history of every direction, thinned, not only its
  last pass. When the calibration wanders (ρ = q/s² > 0, from ``tracker_memory.WanderRate``) the
  times are read on the information clock −log(1 + ρ·age), on which a sample's weight falls
  evenly, so the kept samples thin out with age as fast as their weight does; samples from
  before a sudden change (an *epoch* ago, ``tracker.Tracker``) go before any other. The
  tracker's memory.

Each cell has a home block of ``per_cell`` slots. Re-filing about a new centre (``rebin``) can
give one cell more than ``per_cell`` samples: under ``THIN`` the cell keeps its newest; under
``REFUSE`` nothing kept is given up — the surplus goes to slots other cells leave free, and the
cell takes no newcomer until it is below ``per_cell`` again (the buffer as a whole takes none
once every slot is used). Every sample also records its order of arrival and which visit to its
cell it came in (a visit ends when a sample goes to another cell), which ``WanderRate`` uses
(``pairs``).

The state (``to_state``) holds the geometry, the policy and the samples; ``from_state`` also
reads the state of the session's earlier buffer (``field_ut``: samples in arrival order, an
``aux`` dict each with its time) as a REFUSE buffer holding every one of those samples, counted
about that state's centre as the earlier buffer counted them. The tracker's states, which hold
the samples without the geometry, load with ``load_state`` into a buffer of the tracker's size.
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np

from .coverage import DEFAULT_BANDS, DEFAULT_SECTORS, cell_index


class WhenFull(str, Enum):
    """What a full cell gives up to a new sample (see the module docstring)."""

    REFUSE = "refuse"  # the newcomer: first come, first kept
    THIN = "thin"  # the older of the two samples closest in time


def _whole_positive(v) -> bool:
    try:
        return int(v) == v and v >= 1
    except (TypeError, ValueError, OverflowError):
        return False


class CellBuffer:
    """At most ``per_cell`` samples (µT, with times in s) per equal-area direction cell."""

    _ARRAYS = ("m", "t", "valid", "cell_of", "seq", "visit_of", "epoch_of")

    def __init__(self, bands: int = DEFAULT_BANDS, sectors: int = DEFAULT_SECTORS, per_cell: int = 8, *,
                 when_full: WhenFull = WhenFull.THIN, min_share: float = 0.0, centre_ut=None):
        for name, v in (("bands", bands), ("sectors", sectors), ("per_cell", per_cell)):
            if not _whole_positive(v):
                raise ValueError(f"a sample buffer's {name} must be an integer ≥ 1, not {v!r}")
        if not isinstance(when_full, WhenFull):
            raise ValueError(f"a sample buffer's when_full must be a WhenFull, not {when_full!r}")
        self.bands, self.sectors, self.per_cell = int(bands), int(sectors), int(per_cell)
        self.when_full, self.min_share = when_full, float(min_share)
        cells = self.bands * self.sectors
        cap = cells * self.per_cell
        self.m = np.zeros((cap, 3))
        self.t = np.zeros(cap)
        self.valid = np.zeros(cap, bool)
        self.cell_of = np.zeros(cap, np.int64)  # a slot's cell (its home block's, but for a surplus)
        self.seq = np.zeros(cap, np.int64)  # order of arrival (1, 2, …)
        self.visit_of = np.zeros(cap, np.int64)
        self.epoch_of = np.zeros(cap, np.int64)  # sudden changes seen before the sample came
        self.epoch = 0
        self.count = np.zeros(cells, np.int64)
        self.visits = np.zeros(cells, np.int64)
        self.seq_count = 0
        self.last_cell = -1
        self.centre_ut = centre_ut
        self.rho_per_s = 0.0  # how fast old samples lose weight (q/s², set by the tracker)

    # -- geometry ----------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return len(self.valid)

    @property
    def centre_ut(self) -> np.ndarray | None:
        """The centre the directions are taken about (None until set)."""
        return None if self._centre is None else np.array(self._centre)

    @centre_ut.setter
    def centre_ut(self, centre) -> None:
        self._centre = None if centre is None else tuple(float(v) for v in np.asarray(centre, np.float64).reshape(3))

    def cell(self, x: float, y: float, z: float) -> int:
        """The cell of one sample's direction about the centre (``coverage.cell_index``, scalar)."""
        cx, cy, cz = self._centre
        dx, dy, dz = x - cx, y - cy, z - cz
        norm = math.sqrt(dx * dx + dy * dy + dz * dz) or 1.0
        band = min(int((dz / norm + 1.0) * 0.5 * self.bands), self.bands - 1)
        sector = min(int((math.atan2(dy, dx) + math.pi) / (2.0 * math.pi) * self.sectors), self.sectors - 1)
        return band * self.sectors + sector

    # -- filing ------------------------------------------------------------------------------
    def add(self, x: float, y: float, z: float, t_s: float) -> bool:
        """File one sample (its direction about the centre; a buffer without one takes this
        sample's place as it); False when a full cell refused it (``WhenFull.REFUSE``)."""
        if self._centre is None:
            self._centre = (x, y, z + 1e-9)
        k = self.per_cell
        cell = self.cell(x, y, z)
        lo = cell * k
        n = int(self.count[cell])
        if n < k:
            slot = lo + n if not self.valid[lo + n] else self._free(lo)
            if slot is None:
                return False
            self.count[cell] = n + 1
        elif self.when_full is WhenFull.REFUSE:
            return False
        else:
            slot = self._thinned(lo, t_s)
        self.m[slot] = (x, y, z)
        self.cell_of[slot] = cell
        self.t[slot] = t_s
        self.valid[slot] = True
        self.seq_count += 1
        self.seq[slot] = self.seq_count
        if cell != self.last_cell:
            self.visits[cell] += 1
            self.last_cell = cell
        self.visit_of[slot] = self.visits[cell]
        self.epoch_of[slot] = self.epoch
        return True

    def _free(self, lo: int) -> int | None:
        """A free slot in the home block at ``lo``, else anywhere (a surplus re-filing left in
        that block); None when every slot is used."""
        free = np.flatnonzero(~self.valid[lo:lo + self.per_cell])
        if len(free):
            return lo + int(free[0])
        free = np.flatnonzero(~self.valid)
        return int(free[0]) if len(free) else None

    def _thinned(self, lo: int, t_s: float) -> int:
        """The slot a full cell (its home block at ``lo``: under ``THIN`` the cell's samples and
        only those) gives up."""
        k = self.per_cell
        ep = self.epoch_of[lo:lo + k]
        if int(ep.min()) < self.epoch:  # a sample from before a sudden change goes first, oldest first
            old = np.flatnonzero(ep == ep.min())
            return lo + int(old[np.argmin(self.t[lo:lo + k][old])])
        rho = self.rho_per_s  # else the older of the two samples closest on the information clock
        if rho > 0:
            tt = [-math.log1p(rho * max(t_s - a, 0.0)) for a in self.t[lo:lo + k].tolist()]
        else:
            tt = self.t[lo:lo + k].tolist()
        order = sorted(range(k), key=tt.__getitem__)
        gaps = [tt[order[i + 1]] - tt[order[i]] for i in range(k - 1)]
        return lo + order[gaps.index(min(gaps))]

    def rebin(self, centre, force: bool = False) -> bool:
        """Re-file the kept samples about a new centre, each cell's first in its home block; a
        cell given more than ``per_cell`` keeps its newest under THIN, all under REFUSE (the
        surplus in the slots left free). Refused (unless forced) when fewer cells would be
        occupied than now: a centre that crowds the samples into few cells would starve the fit
        of the directions it needs."""
        centre = np.asarray(centre, dtype=np.float64).reshape(3)
        idx = np.flatnonzero(self.valid)
        cells = cell_index(self.m[idx] - centre, self.bands, self.sectors)
        if not force and len(np.unique(cells)) < self.occupied():
            return False
        k = self.per_cell
        first = self.seq[idx] if self.when_full is WhenFull.REFUSE else -self.t[idx]
        order = np.lexsort((first, cells))  # by cell, the ones kept first
        cells, src = cells[order], idx[order]
        rank = np.arange(len(cells)) - np.searchsorted(cells, cells, side="left")
        if self.when_full is WhenFull.THIN:
            src, cells, rank = src[rank < k], cells[rank < k], rank[rank < k]
        home = rank < k
        slots = cells * k + rank
        slots[~home] = np.setdiff1d(np.arange(self.capacity), slots[home])[: int(np.count_nonzero(~home))]
        moved = {a: getattr(self, a)[src].copy() for a in self._ARRAYS}
        moved["cell_of"] = cells
        self.valid[:] = False
        for a, v in moved.items():
            getattr(self, a)[slots] = v
        self.count[:] = np.bincount(cells, minlength=len(self.count))
        self.centre_ut = centre
        return True

    # -- reading -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.count.sum())

    @property
    def field_ut(self) -> np.ndarray:
        """The kept samples (N, 3) µT in their order of arrival."""
        idx = np.flatnonzero(self.valid)
        return self.m[idx[np.argsort(self.seq[idx], kind="stable")]]

    def samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(slots, m (N, 3), t (N,), cell weight (N,), mean 1): each occupied cell carries the
        same total weight, a cell's count floored at ``min_share`` of a full cell."""
        idx = np.flatnonzero(self.valid)
        cnt = self.count[self.cell_of[idx]]
        w = 1.0 / np.maximum(cnt, max(self.min_share * self.per_cell, 1e-12))
        return idx, self.m[idx], self.t[idx], (w / w.mean() if len(w) else w)

    def occupied(self) -> int:
        return int(np.count_nonzero(self.count))

    def coverage(self) -> float:
        """Share (0…1) of the cells holding at least one sample."""
        return self.occupied() / len(self.count)

    def cell_counts(self) -> np.ndarray:
        """Samples kept in each equal-area cell (band-major: ``band * sectors + sector``)."""
        return self.count.copy()

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
        ok &= self.cell_of[cand] == self.cell_of[new][:, None]  # (a surplus is never paired)
        u = self.m - np.asarray(offset_ut)
        u /= np.maximum(np.linalg.norm(u, axis=1), 1e-300)[:, None]
        cos = np.where(ok, np.einsum("ij,ikj->ik", u[new], u[cand]), -np.inf)
        has = ok.any(axis=1)
        old = cand[np.arange(len(new)), np.argmax(cos, axis=1)][has]
        new = new[has]
        c = np.clip(np.einsum("ij,ij->i", u[new], u[old]), -1.0, 1.0)
        return (e[pos[new]] - e[pos[old]], np.arccos(c), self.visit_of[new] != self.visit_of[old],
                self.t[new] - self.t[old])

    # -- state -------------------------------------------------------------------------------
    def to_state(self) -> dict:
        idx = np.flatnonzero(self.valid)
        return {
            "bands": self.bands, "sectors": self.sectors, "per_cell": self.per_cell,
            "when_full": self.when_full.value, "min_share": self.min_share,
            "slots": idx.tolist(), "cell_of": self.cell_of[idx].tolist(), "m": self.m[idx].tolist(),
            "t": self.t[idx].tolist(),
            "seq": self.seq[idx].tolist(), "visit_of": self.visit_of[idx].tolist(),
            "epoch_of": self.epoch_of[idx].tolist(), "epoch": self.epoch,
            "visits": self.visits.tolist(), "seq_count": self.seq_count, "last_cell": self.last_cell,
            "centre": None if self._centre is None else list(self._centre), "rho_per_s": self.rho_per_s,
        }

    @classmethod
    def from_state(cls, d: dict) -> "CellBuffer":
        """The buffer ``to_state`` gave, or one re-filed from the session's earlier state (its
        samples in arrival order, ``field_ut``); ValueError when ``d`` is malformed."""
        try:
            geometry = (int(d["bands"]), int(d["sectors"]), int(d["per_cell"]))
            if "field_ut" in d:
                return cls._first_come(geometry, d)
            buf = cls(*geometry, when_full=WhenFull(d["when_full"]), min_share=float(d["min_share"]))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"sample buffer state is malformed: {exc!r}") from None
        buf.load_state(d)
        return buf

    @classmethod
    def _first_come(cls, geometry: tuple[int, int, int], d: dict) -> "CellBuffer":
        """A REFUSE buffer holding every sample of the earlier state, in their order of arrival,
        filed about its centre (as that buffer counted them: a cell may hold a surplus)."""
        buf = cls(*geometry, when_full=WhenFull.REFUSE)
        m = np.asarray(d["field_ut"], dtype=np.float64).reshape(-1, 3)
        n = len(m)
        if n > buf.capacity:
            raise ValueError("sample set state holds more samples than its capacity")
        aux = list(d.get("aux") or [{}] * n)
        if len(aux) != n:
            raise ValueError(f"sample set state has {n} samples but {len(aux)} aux entries")
        buf.m[:n], buf.valid[:n], buf.seq[:n], buf.seq_count = m, True, np.arange(1, n + 1), n
        buf.t[:n] = [float(a.get("t_s", 0.0)) for a in aux]  # (no time: 0, which first come never reads)
        buf.rebin(d["centre_ut"], force=True)
        return buf

    def load_state(self, d: dict) -> None:
        """Take the samples and counters of ``to_state`` (a state without its geometry is taken
        as this buffer's)."""
        for name in ("bands", "sectors", "per_cell"):
            if name in d and int(d[name]) != getattr(self, name):
                raise ValueError(f"sample buffer state has {name} {d[name]}, this buffer {getattr(self, name)}")
        idx = np.asarray(d["slots"], dtype=np.int64)
        if len(idx) and (idx.min() < 0 or idx.max() >= len(self.valid)):
            raise ValueError("sample buffer state does not fit this buffer's size")
        self.m[idx] = np.asarray(d["m"], dtype=np.float64).reshape(-1, 3)
        self.t[idx] = np.asarray(d["t"], dtype=np.float64)
        self.seq[idx] = np.asarray(d["seq"], dtype=np.int64)
        self.visit_of[idx] = np.asarray(d["visit_of"], dtype=np.int64)
        self.epoch_of[idx] = np.asarray(d["epoch_of"], dtype=np.int64)
        self.epoch = int(d["epoch"])
        cells = np.asarray(d["cell_of"], dtype=np.int64) if "cell_of" in d else idx // self.per_cell
        if len(cells) != len(idx) or (len(cells) and (cells.min() < 0 or cells.max() >= len(self.count))):
            raise ValueError("sample buffer state's cells do not fit this buffer")
        self.cell_of[idx] = cells  # (states saved before surpluses: each slot in its home block)
        self.valid[idx] = True
        self.count[:] = np.bincount(cells, minlength=len(self.count))
        self.visits[:] = np.asarray(d["visits"], dtype=np.int64)
        self.seq_count, self.last_cell = int(d["seq_count"]), int(d["last_cell"])
        self.centre_ut = d["centre"]
        self.rho_per_s = float(d["rho_per_s"])
