"""The twin as the null: residuals drawn from the recording's own sensor twin, with no term.

A test of a candidate term (soft iron, an offset following a channel) asks how often a residual
with *no* such term would give a statistic as large. Referred to white noise (the F
distribution), a slow channel on a real recording is credited with the recording's own wander
whenever the two happen to line up. Here the question is put to the recording's twin instead:

1. the twin is learned from the residual the tests themselves see — the reference model's,
   with every candidate term and every nuisance of the design fitted out except the wander
   (``learn``): the offset wander as the sensor model's fitted process (magcal.sim.wander.fit,
   by simulated moments through the same projection), the white noise and the quantum
   (magcal.diagnose.lattice.quantum). With the candidate terms fitted, an effect that is there is
   not taken for wander (a simulated temperature cycle would otherwise come back as wander of
   its own size); with soft iron fitted along all five directions, also those the tests leave
   out (design.Design.x_candidates), soft iron the data do not pin is not taken for wander
   either — on a band swept with a period it is a periodic signal in time, and left in, a
   white simulation's twin learned it as 0.08 µT of wander at the sweep's own frequency;
2. ``draws``: the twin (a magcal.sim.model.SensorModel), driven by the recording's own
   directions, times and channels and without any candidate term, is drawn ``count`` times;
   each draw's radial residual about the twin's own calibration is what the recording's
   residual would be with no term and with its wander, to first order (the design's columns
   are linear in the same way);
3. every test runs on those residuals too (inference.block_wald ``null=``), and is judged
   against them (inference.calibrated): one set of draws serves every test of the recording.

On a simulated recording without wander the twin is white and the tests keep the F
distribution's power; on a real one the twin wanders as the recording does and a chance
alignment is judged as such.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..core.calibration import Calibration

DRAWS = 24
WHITE_LEVEL = 0.05  # a residual whose block sums are consistent with white noise at this level gets no twin
SEED = 0x7E1
FIT_SEEDS = (11,)


@dataclass(frozen=True)
class NullDraws:
    """Residuals of the recording's twin with no candidate term."""

    e: np.ndarray  # (n, K) radial residual draws (µT), one column per draw
    white: np.ndarray  # (n, K) the same draws without the twin's wander (the white noise and quantum alone)
    model: object | None  # the SensorModel they were drawn from (None: none could be learned)
    why_not: str = ""  # when no draws were made: why (the tests are then referred to F alone)

    @property
    def count(self) -> int:
        return self.e.shape[1]

    def to_dict(self) -> dict:
        """What the tests were judged against, for the JSON."""
        if self.model is None or not self.count:
            return {"draws": 0, "why_not": self.why_not}
        return {"draws": self.count, "noise_ut": self.model.noise_ut[0], "quantum_ut": list(self.model.quantum_ut),
                "wander": [c.to_dict() for c in self.model.wander]}


def white_p(residual_ut: np.ndarray, blocks: list) -> float:
    """p of the residual's block sums under white noise: Σ_b S_b² / (σ² n_b) against χ² with
    one degree of freedom per block less one (the level is fitted). A residual with no sign
    of wander gets no twin: a wander fitted to chance structure would only cost the tests
    power, and the bias-corrected block covariance keeps the F distribution for white noise."""
    from ..fit.tails import chi2_sf

    r = np.asarray(residual_ut, np.float64)
    var = float(r @ r) / max(len(r), 1)
    if var <= 0 or len(blocks) < 3:
        return 1.0
    q = sum(float(r[b].sum()) ** 2 / (b.stop - b.start) for b in blocks) / var
    return chi2_sf(q, len(blocks) - 1)


def learn(residual_ut: np.ndarray, project, m: np.ndarray, t: np.ndarray, u: np.ndarray, calibration: Calibration):
    """The twin of the residual the tests see: ``residual_ut`` (n,) with the design's columns
    other than the wander fitted out, ``project`` the same projection for any radial series
    (what the design's fit absorbs), on directions ``u`` at times ``t``; ``m`` the samples
    (µT) for the quantum; ``calibration`` the deterministic part. A SensorModel."""
    from ..sim import wander
    from ..sim.model import SensorModel
    from .lattice import quantum

    # one seed of simulated moments per candidate: a binned periodogram over many frequencies
    # is already an average, and the test only needs the wander's spectrum roughly
    components, white = wander.fit(residual_ut, u, t, project, seeds=FIT_SEEDS, flat_below=True)
    q = quantum(m)
    white -= float(np.mean(u**2 @ (np.square(q) / 12.0)))  # what the quantum adds to the white part
    sigma = float(np.sqrt(max(white, 1e-12)))
    return SensorModel(calibration=calibration, noise_ut=(sigma,) * 3, quantum_ut=q, wander=components,
                       rate_hz=1.0 / wander.sample_interval(t))


def draws(model, u: np.ndarray, t: np.ndarray, chans: Mapping[str, np.ndarray], count: int = DRAWS,
          seed: int = SEED) -> NullDraws:
    """``count`` radial residual draws of ``model`` (a SensorModel) without its channel terms
    (the null: no candidate term) on directions ``u`` at times ``t``, each about the model's
    own calibration. To first order in the random parts (as the design's columns are linear),
    the radial residual of a draw is the twin's own random parts (SensorModel.draws: the offset
    wander's path and the white noise) and the quantum's rounding error, each along the field
    direction: that, not the full distort-and-correct round trip, is what is drawn."""
    for c in model.calibration.coef_ut_per_unit:
        model = model.without(c)
    if not any(np.any(np.asarray(c.sigma_ut) > 0) for c in model.wander):
        # a white twin: every draw equals its own wander-free copy, λ = 1, the F distribution holds
        return NullDraws(np.zeros((len(u), 0)), np.zeros((len(u), 0)), model, "the twin has no wander")
    u = np.asarray(u, np.float64)
    q = np.asarray(model.quantum_ut, np.float64)
    noise = np.asarray(model.noise_ut, np.float64)
    out = np.empty((len(u), count))
    white = np.empty((len(u), count))
    for k in range(count):
        parts = model.draws(t, seed + k)
        v = noise * parts.noise
        if np.any(q > 0):  # rounding to the quantum: uniform within ±q/2 on each axis
            v = v + q * (np.random.default_rng([seed + k, 0x9A]).random(v.shape) - 0.5)
        white[:, k] = np.einsum("ij,ij->i", u, v)
        out[:, k] = white[:, k] + np.einsum("ij,ij->i", u, parts.wander_ut)
    return NullDraws(out, white, model)


def none(n: int, why: str) -> NullDraws:
    return NullDraws(np.zeros((n, 0)), np.zeros((n, 0)), None, why)
