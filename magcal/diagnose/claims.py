"""Claims only where the data determine them: each accepted term checked before it is a finding.

A term the tests accepted is reported as a finding only when

- **the halves agree**: the model refitted on the first and on the second half of the recording
  (in time) gives the term's parameters within their uncertainties (each half's covariance
  widened by its own residual's correlation in time, ``locate.steps_scan.inflation``), χ² at
  ``HALVES_LEVEL`` — or, where a slightly misspecified model makes that test too sharp, within
  ``MAX_HALVES_SHARE`` of the term's own size; a half that cannot determine the term leaves the
  check untestable, not failed;
- **it is physically plausible**: a drift in time moves the offset by less than
  ``MAX_DRIFT_SHARE`` of the field over the recording, and soft iron spreads the axis gains by less
  than ``MAX_GAIN_SPREAD``. Beyond those a field that varies with position, or a motion the model
  cannot separate, is the likelier cause.

A term that fails is dropped from the model (it never changes the returned calibration) and
stated as a limit with its reason.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from ..fit.tails import chi2_sf

from . import channels, softiron, statements, timewords
from .limits import Limit
from .locate.steps_scan import inflation
from .model import FitFailure, ModelFit, fit_model

HALVES_LEVEL = 1e-3
# the terms whose halves are compared: a drift in time. Soft iron and the channels' offsets were
# tried too, and refused true terms on bands of directions and beside a temperature over 1.3
# cycles (their halves' fits are nearly collinear with the drift nuisance there, and their
# covariance does not show it), so they are judged by plausibility alone for now.
HALVES_CHECKED = (channels.TIME,)
MAX_HALVES_SHARE = 0.5  # the halves may differ by this share of the term's size before it counts
MAX_DRIFT_SHARE = 0.15  # of the field, over the whole recording
MAX_GAIN_SPREAD = 0.30  # largest over smallest axis gain of W, less one
BLOCKS = 20


@dataclass(frozen=True)
class Refused:
    """A term the tests accepted that the checks refuse, and why."""

    group: str
    reason: str

    def limit(self) -> Limit:
        return Limit(self.group, True, f"A {self.group.replace('_', ' ')} term passed the tests but is not reported as "
                                       f"a finding: {self.reason}. The calibration is returned without it.",
                     details={"check": "claims"})


def term_index(spec, group: str, channel: str | None) -> np.ndarray:
    """The positions of one term's parameters in a ModelFit's parameter vector."""
    k = 4 + spec.n_soft
    if group == softiron.EFFECT:
        return np.arange(3, 3 + spec.n_soft)
    j = spec.channels.index(channel)
    return np.arange(k + 3 * j, k + 3 * j + 3)


def halves_disagree(m, t, chans, final: ModelFit, group: str, channel: str | None) -> str | None:
    """The reason the two halves in time contradict a term — they disagree with each other, or
    both with the whole recording's estimate (a step or a wander fitted as a drift: each half
    shows none) — or None (they agree, or a half cannot determine it)."""
    fits = _half_fits(m, t, chans, final, group, channel)
    if fits is None:
        return None
    (a, ca), (b, cb) = fits
    whole = final.params[term_index(final.spec, group, channel)]
    size = max(float(np.linalg.norm(whole)), 1e-12)
    for d, s, what in ((a - b, ca + cb, "the two halves of the recording disagree on it"),
                       ((a + b) / 2 - whole, (ca + cb) / 4, "each half of the recording shows far less of it than the whole")):
        p, chi2 = _chi2_p(d, s)
        share = float(np.linalg.norm(d)) / size
        if p < HALVES_LEVEL and share > MAX_HALVES_SHARE:
            return (f"{what} ({share:.0%} of its size apart; χ² {chi2:.1f} on {len(d)} degrees of freedom, p = {p:.1g}, "
                    "with each half's own correlation in time counted)")
    return None


def one_jump(m, t, chans, final: ModelFit) -> str | None:
    """The reason a drift in time has the wrong shape — without it, most of the offset's wander
    is one jump (statements.measure_wander, at ``HALVES_LEVEL``), which a straight line only
    approximates — or None."""
    spec = replace(final.spec, channels=tuple(c for c in final.spec.channels if c != channels.TIME))
    f = fit_model(m, {c: chans[c] for c in spec.channels}, spec, final.reference, start=final)
    jump = None if isinstance(f, FitFailure) else statements.measure_wander(f, m, chans, t, HALVES_LEVEL).jump
    if jump is None:
        return None
    a, b = jump.interval_s
    return (f"without it, {jump.share:.0%} of the offset's wander is one jump of {np.linalg.norm(jump.jump_ut):.2f} µT "
            f"somewhere in {timewords.stretch(a, b)} (p = {jump.p_value:.1g} beyond a slow wander), not a steady drift")


def _chi2_p(d: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    try:
        chi2 = float(d @ np.linalg.solve(s, d))
    except np.linalg.LinAlgError:
        return 1.0, 0.0
    return float(chi2_sf(chi2, len(d))), chi2


def _half_fits(m, t, chans, final: ModelFit, group: str, channel: str | None) -> list | None:
    """(parameters, covariance) of the term in each half's own fit; None where a half cannot
    determine it."""
    half = len(m) // 2
    spec, start = _with_drift(final, channel)
    fits = []
    for sl in (slice(0, half), slice(half, None)):
        part = {c: v[sl] for c, v in chans.items()}
        part.setdefault(channels.TIME, t[sl])
        ref = {**final.reference, channels.TIME: float(np.median(t[sl]))}
        f = fit_model(m[sl], part, spec, ref, start=start)
        if isinstance(f, FitFailure) or f.cov is None or not _determines(f, m[sl], group):
            return None
        idx = term_index(f.spec, group, channel)
        r = f.residual(m[sl], part)
        cov = f.cov[np.ix_(idx, idx)] * inflation(r, np.ones((len(r), 1)), len(r) // BLOCKS)
        if not np.all(np.isfinite(cov)):
            return None
        fits.append((f.params[idx], cov))
    return fits


def _determines(f: ModelFit, m: np.ndarray, group: str) -> bool:
    """Whether a half's own directions determine every soft-iron direction the model carries
    (halves of a single sweep see different directions: there the check cannot be made)."""
    if group != softiron.EFFECT:
        return True
    dirs = softiron.determined_directions(m, f.offset_ut, f.rms_ut)
    return dirs.shape[1] >= f.spec.n_soft


def _with_drift(final: ModelFit, channel: str | None) -> tuple:
    """The spec each half is fitted with: ``final``'s, plus — for a channel term — a linear drift
    in time as a nuisance (a slow wander within a half would otherwise pass for a disagreement;
    beside soft iron on a band of directions a drift stands in for the soft iron itself)."""
    if channels.TIME in final.spec.channels or channel in (channels.TIME, None):
        return final.spec, final
    return replace(final.spec, channels=final.spec.channels + (channels.TIME,)), final


def implausible(final: ModelFit, group: str, channel: str | None, t: np.ndarray) -> str | None:
    """The reason a term's size is physically implausible here, or None."""
    field = float(final.calibration().field_ut)
    if channel == channels.TIME:
        drift = float(np.linalg.norm(final.coef_ut_per_unit[channel]) * (t[-1] - t[0]))
        if drift > MAX_DRIFT_SHARE * field:
            return (f"it would move the offset by {drift:.1f} µT over {timewords.duration(t[-1] - t[0], '.0f')}, more than "
                    f"{MAX_DRIFT_SHARE:.0%} of the {field:.1f} µT field — a field that varies with position, or a motion "
                    "the model cannot separate from a drift, is likelier")
    if group == softiron.EFFECT:
        g = np.linalg.svd(final.soft_iron, compute_uv=False)
        spread = float(g.max() / g.min() - 1.0)
        if spread > MAX_GAIN_SPREAD:
            return (f"it would spread the axis gains by {spread:.0%}, beyond what a sensor's own gains or nearby iron "
                    "make plausible — a field that varies with position, or directions the motion leaves unpinned, "
                    "is likelier")
    return None


def screen(m, t, chans, final: ModelFit, accepted: list, candidates: dict) -> tuple[list, tuple[Refused, ...]]:
    """(the accepted groups that pass both checks, the refused ones with their reasons)."""
    kept, refused = [], []
    for g in accepted:
        channel = candidates[g].channel if g in candidates else None
        if g != softiron.EFFECT and (channel is None or channel not in final.spec.channels):
            kept.append(g)
            continue
        if g == softiron.EFFECT and not final.spec.soft_iron:
            kept.append(g)
            continue
        why = implausible(final, g, channel, t)
        if why is None and channel in HALVES_CHECKED:
            why = halves_disagree(m, t, chans, final, g, channel)
        if why is None and channel == channels.TIME:
            why = one_jump(m, t, chans, final)
        (refused.append(Refused(g, why)) if why else kept.append(g))
    return kept, tuple(refused)


def without(selected, kept: list):
    """``selected`` with only ``kept`` accepted."""
    return replace(selected, accepted=list(kept))
