"""The evidence behind a calibration, from the samples it was fitted on: what the write gates
judge (``logic.gates.Evidence``), so that every result carries it and ``magcal write`` can
recompute it from the recording a result names.

``evidence(m_ut, cal, channels)`` gives, for the samples ``m_ut`` (n, 3, µT, in time order) and
the calibration ``cal`` (its channel terms applied where ``channels`` holds their columns):

* ``n_used``: how many;
* ``coverage``: the share of equal-area cells holding a calibrated direction — the session's
  own measure (``fit.coverage``);
* ``condition``: the condition of the sphere's normal matrix, as the session's live estimate
  reports it (``SphereAccumulator``);
* ``rms_ut``: the residual RMS of |W (m − b − Σ k·(x − x₀))| about the field;
* ``offset_sigma_ut``: the offset's 1σ per axis from the batch-means sandwich on contiguous
  blocks (``uncertainty.block_covariance``: robust to residuals correlated over less than a
  block), mapped from the calibrated frame back to the raw one.
"""

from __future__ import annotations

import numpy as np

from ..core.calibration import Calibration
from . import geometric, uncertainty
from .accumulator import SphereAccumulator
from .coverage import coverage


def evidence(m_ut, cal: Calibration, channels=None) -> dict:
    """The gates' evidence for ``cal`` on samples ``m_ut`` (``channels``: their columns by
    name, for the calibration's channel terms); JSON-ready. A quantity the numbers cannot give
    (a calibration so far off that nothing stays finite) is None: its gate is left unjudged."""
    m = np.asarray(m_ut, dtype=np.float64).reshape(-1, 3)
    out = {"n_used": 0, "coverage": None, "condition": None, "rms_ut": None, "offset_sigma_ut": None}
    with np.errstate(all="ignore"):
        moved = m - cal.offset_ut - cal.channel_offset_ut(channels, len(m))
        c = moved @ cal.soft_iron.T
        good = np.all(np.isfinite(c), axis=1)
        m, c = m[good], c[good]
        out["n_used"] = int(len(m))
        if len(m) == 0:
            return out
        try:
            out.update(_measures(m, c, cal))
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            pass
    return {k: _finite_or_none(v) for k, v in out.items()}


def _measures(m: np.ndarray, c: np.ndarray, cal: Calibration) -> dict:
    norm = np.linalg.norm(c, axis=1)
    good = norm > 0
    acc = SphereAccumulator()
    acc.add_batch(m)
    sphere = acc.solve(max_condition=float("inf"))
    return {"coverage": round(float(coverage(c[good] / norm[good, None])), 4) if good.any() else 0.0,
            "condition": float(sphere.condition) if sphere else None,
            "rms_ut": float(np.sqrt(np.mean((norm - cal.field_ut) ** 2))),
            "offset_sigma_ut": _offset_sigma(c, cal.field_ut, cal.soft_iron)}


def _finite_or_none(v):
    if isinstance(v, list):
        return v if all(np.isfinite(x) for x in v) else None
    return v if v is None or np.isfinite(v) else None


def _offset_sigma(c: np.ndarray, field_ut: float, w: np.ndarray) -> list[float] | None:
    """1σ per raw axis of the offset, from the calibrated samples ``c`` about the origin."""
    if len(c) < 8:
        return None
    theta = geometric.pack(np.zeros(3), field_ut, "sphere")
    res, jac = geometric.residual_jacobian(theta, c, "sphere")
    cov = uncertainty.block_covariance(jac, res)[:3, :3]
    try:
        w_inv = np.linalg.inv(w)
    except np.linalg.LinAlgError:
        return None
    raw = w_inv @ cov @ w_inv.T
    sig = np.sqrt(np.clip(np.diag(raw), 0.0, None))
    return [float(v) for v in sig] if np.all(np.isfinite(sig)) else None
