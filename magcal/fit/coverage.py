"""Direction coverage on the sphere, in equal-area cells.

The sphere is cut into ``bands`` zones of equal height in z (equal area, by Archimedes' hat-box
theorem) and each zone into ``sectors`` equal longitude sectors, so every cell has the same area
4π/(bands·sectors). Coverage is the share of cells holding at least one sample direction.

The cells are also the bins of the one sample buffer, ``cell_buffer.CellBuffer``, which keeps
a bounded, well-spread subset of the stream (at most ``per_cell`` samples a cell) for the
session's final fit and for the tracker.
"""

from __future__ import annotations

import numpy as np

from .geometric import row_norm

DEFAULT_BANDS = 8
DEFAULT_SECTORS = 16


def cell_index(directions: np.ndarray, bands: int = DEFAULT_BANDS, sectors: int = DEFAULT_SECTORS) -> np.ndarray:
    """Equal-area cell of each unit (or any non-zero) vector, (n, 3) → (n,) ints."""
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    norm = row_norm(d)  # np.linalg.norm's sums, in its order
    norm[norm == 0] = 1.0
    z = np.clip(d[:, 2] / norm, -1.0, 1.0)
    band = np.minimum(((z + 1.0) / 2.0 * bands).astype(np.int64), bands - 1)
    lon = np.arctan2(d[:, 1], d[:, 0])
    sector = np.minimum(((lon + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)
    return band * sectors + sector


def coverage(directions: np.ndarray, bands: int = DEFAULT_BANDS, sectors: int = DEFAULT_SECTORS) -> float:
    """Share (0…1) of equal-area cells that hold at least one direction."""
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    if len(d) == 0:
        return 0.0
    return len(np.unique(cell_index(d, bands, sectors))) / float(bands * sectors)


def cell_centres(bands: int = DEFAULT_BANDS, sectors: int = DEFAULT_SECTORS) -> np.ndarray:
    """Unit vectors at the centre of each cell, in ``cell_index`` order (band-major)."""
    z = -1.0 + (2 * np.arange(bands) + 1) / bands
    lon = -np.pi + (2 * np.arange(sectors) + 1) * np.pi / sectors
    zz, ll = np.meshgrid(z, lon, indexing="ij")
    r = np.sqrt(1 - zz**2)
    return np.stack([r * np.cos(ll), r * np.sin(ll), zz], axis=-1).reshape(-1, 3)


def nearest_empty_cell(counts, bands: int, sectors: int, direction) -> tuple[int, float] | None:
    """The empty cell nearest to ``direction`` (any vector; None: the first empty cell) and the
    angle to it in degrees (nan without a direction); None when no cell is empty."""
    empty = np.flatnonzero(np.asarray(counts) == 0)
    if len(empty) == 0:
        return None
    if direction is None:
        return int(empty[0]), float("nan")
    u = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(u))
    if not norm > 0 or not np.isfinite(norm):
        return int(empty[0]), float("nan")
    cosang = np.clip(cell_centres(bands, sectors)[empty] @ (u / norm), -1.0, 1.0)
    k = int(np.argmax(cosang))
    return int(empty[k]), float(np.degrees(np.arccos(cosang[k])))


def side_name(direction) -> str:
    """The side of the sensor a direction points out of: ``−Z``, ``+X/−Z`` (strongest first)."""
    u = np.asarray(direction, dtype=np.float64)
    u = u / (np.linalg.norm(u) or 1.0)
    order = np.argsort(-np.abs(u))
    parts = [("+" if u[i] >= 0 else "−") + "XYZ"[i] for i in order if abs(u[i]) >= 0.38]
    return "/".join(parts[:2]) or "+X"
