"""The calibration the tracker reports: its model one fit's gates accept, its σ at least fit's.

The tracker (``tracker``) climbs sphere → diagonal → full ellipsoid on gates of its own, judged
on its weighted memory at every refit, and states the σ of its weighted solve. ``fit``
(``pipeline``) judges the same questions with more care — the shape σ at the shared noise and
with the diagonal's residual correlation, a superset refused where its subset is undetermined,
σ widened by the residuals' correlation in time and by how much the answer depends on which
directions were seen — at tens of ms a call. So the tracker's estimate is checked where a
calibration is *reported* (the end of ``magcal track``, the keeper's decision to write), never
per sample, which keeps the tracker's cost per sample:

* **Model.** fit is run on the samples in memory, in time order, and on the whole recording
  where the caller holds it (``recording``). Where fit's gates refuse the tracker's model on
  any of them, the fullest model they all accept inside it (full → diagonal → sphere) is solved
  on memory with the tracker's own weights, from the tracker's solution, and reported instead
  (``Estimate.refused_model`` names the one refused). Where fit refuses even the sphere,
  nothing is reported.
* **σ.** Each stated σ (offset, field, soft-iron matrix) is at least fit's on each of those
  sample sets: fit's for the model fit chooses, and fit's for the reported model (for a
  diagonal ellipsoid that fit accepts but reports neither as its choice nor as its fullest
  model, the full ellipsoid's, whose σ are the wider).
  Memory alone is not enough where the recording is held: it is thinned in time, and its time
  blocks and direction groups see less of the slow error than the whole recording's do (on the
  open real recordings fit's offset σ on memory was at times a fifth of fit's on the same half).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..core.calibration import Calibration
from . import geometric
from .failure import FitFailure
from .pipeline import fit_models
from .result import MODEL_NAMES
from .tracker import Estimate, Tracker, condition, gauss_newton
from .uncertainty import SPHERE_GAIN_SIGMA, gain_doubt, soft_iron_sigma

KIND_OF = {name: kind for kind, name in MODEL_NAMES.items()}
SOLVE_STEPS = 10  # Gauss–Newton steps for a model the tracker falls back to, from its own solution


@dataclass(frozen=True)
class Sigma:
    """1σ of offset (3), field and soft-iron matrix (3×3)."""

    offset_ut: np.ndarray
    field_ut: float
    soft_iron: np.ndarray

    def at_least(self, other: "Sigma | None") -> "Sigma":
        if other is None:
            return self
        return Sigma(np.fmax(self.offset_ut, other.offset_ut), float(np.fmax(self.field_ut, other.field_ut)),
                     np.fmax(self.soft_iron, other.soft_iron))


@dataclass(frozen=True)
class FitView:
    """What fit says on one set of samples: the models its gates accept (``geometric.KINDS``,
    subset first), the one it chooses, and each reported model's 1σ."""

    accepted: tuple[str, ...]
    chosen: str
    sigma: dict

    def sigma_of(self, kind: str) -> Sigma | None:
        """fit's σ for ``kind``, else for the nearest fuller model it reported (wider)."""
        return next((self.sigma[k] for k in geometric.KINDS[geometric.KINDS.index(kind):] if k in self.sigma), None)


def fit_view(m: np.ndarray) -> FitView | FitFailure:
    """fit's gates and σ on the samples ``m`` (n, 3), in time order."""
    res = fit_models(m, ("auto", "ellipsoid", "sphere"))
    auto = res["auto"]
    if not auto:
        return auto
    sigma = {}
    for r in (res["sphere"], res["ellipsoid"], auto):  # auto last: its sphere states the gains it assumed
        if r:
            u = r.uncertainty
            sigma[KIND_OF[r.model]] = Sigma(np.asarray(u["offset_ut"], float), float(u["field_ut"]),
                                            np.asarray(u["soft_iron"], float))
    return FitView(tuple(k for k in geometric.KINDS if MODEL_NAMES[k] in auto.alternatives), KIND_OF[auto.model], sigma)


def _own_sigma(tracker: Tracker, est: Estimate, kind: str) -> Sigma:
    """The tracker's own σ of its estimate: the offset's as published (widened), field and soft
    iron from its last weighted solve where that solve is the estimate's (else none: fit's stand)."""
    zero = Sigma(np.asarray(est.offset_sigma_ut, float), 0.0, np.zeros((3, 3)))
    solved = tracker.solved
    if solved is None or solved[0] != kind or not np.array_equal(
            solved[1][:3], np.asarray(est.calibration.offset_ut)):
        return zero
    _, theta, A, s2 = solved
    try:
        cov = s2 * np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return zero
    return Sigma(zero.offset_ut, float(np.sqrt(max(cov[3, 3], 0.0))), soft_iron_sigma(theta, kind, cov))


def _assumed_gains(tracker: Tracker, est: Estimate) -> Sigma:
    """A sphere states its axis gains equal by assumption: its soft-iron σ is what gains spread
    as real sensors' are leave after the samples in memory (``uncertainty.gain_doubt``), as
    fit states for a sphere it chose."""
    _, m, _, _ = tracker.memory.samples()
    theta = geometric.pack(est.calibration.offset_ut, est.calibration.field_ut, "sphere")
    e = geometric.residual(theta, m, "sphere")
    s2 = max(est.noise_ut**2, 1e-18)
    return Sigma(np.zeros(3), 0.0, gain_doubt(theta, m, e, SPHERE_GAIN_SIGMA, s2)[1])


def _solve_smaller(tracker: Tracker, est: Estimate, kind: str):
    """The tracker's weighted solve on memory for the smaller model ``kind``, from its estimate:
    (θ, Sigma) or None where the weighted memory does not pin it."""
    idx, m, t, wc = tracker.memory.samples()
    c = est.calibration
    theta0 = geometric.pack(c.offset_ut, c.field_ut, KIND_OF[est.model], c.soft_iron)
    e = geometric.residual(theta0, m, KIND_OF[est.model])
    w, s2 = tracker.weights_now(idx, t, wc, e, est.wander_ut2_per_s)
    start = geometric.pack(c.offset_ut, c.field_ut, kind, c.soft_iron)
    theta, A, _ = gauss_newton(m, kind, start, w, SOLVE_STEPS)
    if condition(A) > tracker.config.max_condition or not theta[3] > 0:
        return None
    try:
        cov = s2 * np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return None
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return theta, Sigma(d[:3], float(d[3]), soft_iron_sigma(theta, kind, cov))


def checked(tracker: Tracker, recording: np.ndarray | None = None) -> Estimate | None:
    """The tracker's estimate as it may be reported (see the module docstring): None where it
    has none, or where fit refuses every model on its memory (or on ``recording``)."""
    est = tracker.estimate
    if est is None:
        return None
    _, m, t, _ = tracker.memory.samples()
    views = [fit_view(m[np.argsort(t, kind="stable")])]
    if recording is not None:
        views.append(fit_view(np.asarray(recording, np.float64)))
    if any(isinstance(v, FitFailure) for v in views):
        return None
    kind = KIND_OF[est.model]
    allowed = [k for k in geometric.KINDS[: geometric.KINDS.index(kind) + 1] if all(k in v.accepted for v in views)]
    for use in reversed(allowed):
        if use == kind:
            reported, own = est, _own_sigma(tracker, est, kind)
        else:
            solved = _solve_smaller(tracker, est, use)
            if solved is None:
                continue
            b, r, W = geometric.unpack(solved[0], use)
            reported = replace(est, model=MODEL_NAMES[use], refused_model=est.model,
                               calibration=Calibration(offset_ut=b, field_ut=r, soft_iron=W))
            own = solved[1]
        if use == "sphere":
            own = own.at_least(_assumed_gains(tracker, reported))
        for v in views:
            own = own.at_least(v.sigma_of(use)).at_least(v.sigma[v.chosen])
        return replace(reported, offset_sigma_ut=own.offset_ut, field_sigma_ut=own.field_ut,
                       soft_iron_sigma=own.soft_iron)
    return None
