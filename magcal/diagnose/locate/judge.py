"""Keep a located effect only where modelling it improves time-blocked held-out prediction.

Each named effect comes with its ``remove`` (``Effect.remove``): the samples with the effect
taken out. The calibration (``magcal fit``'s own procedure, with the model it chose) is fitted
once to every sample, with and without the effect removed; for every contiguous time block its
model is refitted by least squares to the samples fit kept outside the block, with fit's
direction balance where fit gave it (Gauss–Newton from the whole fit, ``magcal.fit.holdout.refit``:
one fit's outliers and model choice for all blocks, not five runs of the whole procedure) and judged on the block it left out; an effect is kept
when its held-out RMS radial residual is lower by more than the scatter of that gain over the
blocks allows to be chance. Effects are judged one after another, largest first, each on the
samples with the ones already kept taken out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...fit import FitFailure, fit_calibration, geometric, holdout
from ...fit.result import MODEL_NAMES
from ..inference import contiguous_blocks
from .base import Effect, Kind, Located

FOLDS = 5
KINDS = {name: kind for kind, name in MODEL_NAMES.items()}  # fit's model name → geometric kind
MIN_GAIN_SIGMAS = 2.0  # the held-out gain must exceed this many standard errors of its block scatter


@dataclass(frozen=True)
class Verdict:
    """One effect judged on held-out blocks: RMS radial residual (µT) without and with it."""

    located: Located
    kept: bool
    heldout_without_ut: float
    heldout_with_ut: float
    reason: str

    @property
    def contradicted(self) -> bool:
        """Modelling it made unseen blocks worse: the recording itself speaks against it."""
        return bool(self.heldout_with_ut >= self.heldout_without_ut)

    def evidence(self) -> dict:
        return {
            "heldout_rms_without_ut": self.heldout_without_ut,
            "heldout_rms_with_ut": self.heldout_with_ut,
            "modelled": self.kept,
            "why": self.reason,
        }


def fitted(m_ut: np.ndarray, model: str, known=()):
    """``fit_calibration(m_ut, model=model)``; ``known``: fit's runs already made, as (model,
    samples, result), one of which is taken where it was made with this model on these very
    samples (the diagnosis runs fit on the same samples as the locate step at times: the samples
    as they are when nothing was set aside, the samples with its channel terms out); a list
    ``known`` gets the run made here."""
    for k_model, samples, result in known:
        if k_model == model and samples.shape == m_ut.shape and np.array_equal(samples, m_ut):
            return result
    result = fit_calibration(m_ut, model=model)
    if isinstance(known, list):
        known.append((model, m_ut, result))
    return result


def heldout_sq(m_ut: np.ndarray, model: str, folds: int = FOLDS, known=()) -> np.ndarray | None:
    """Per block, the mean square radial residual of the calibration refitted without that
    block (see the module docstring); None where the samples or a block's complement cannot be
    fitted. ``known`` as ``fitted`` takes it."""
    whole = fitted(m_ut, model, known)
    if not whole:
        return None
    g = _geometric(whole, m_ut)
    used = np.zeros(len(m_ut), bool)
    used[whole.used] = True
    out = []
    for held in contiguous_blocks(len(m_ut), folds):
        rows = used.copy()
        rows[held] = False
        theta = holdout.refit(m_ut, rows, g, whole.balanced)
        if isinstance(theta, FitFailure):
            return None
        b, field_ut, w = geometric.unpack(theta, g.kind)
        r = np.linalg.norm((m_ut[held] - b) @ w.T, axis=1) - field_ut  # the calibrated radial residual
        out.append(float(np.mean(r**2)))
    return np.asarray(out)


def _geometric(result, m_ut: np.ndarray) -> geometric.GeometricFit:
    """fit's result as its model's geometric fit on every sample of ``m_ut`` (residual and
    Jacobian there: where each block's refit starts)."""
    kind = KINDS[result.model]
    cal = result.calibration
    theta = geometric.pack(cal.offset_ut, cal.field_ut, kind, cal.soft_iron)
    return geometric.GeometricFit(kind, theta, *geometric.residual_jacobian(theta, m_ut, kind), 0)



def compare(before: np.ndarray, after: np.ndarray) -> tuple[bool, str]:
    """Whether the per-block mean squares ``after`` beat ``before`` beyond chance."""
    gain = before - after
    se = np.std(gain, ddof=1) / np.sqrt(len(gain)) if len(gain) > 1 else np.inf
    better = bool(gain.mean() > MIN_GAIN_SIGMAS * se and gain.mean() > 0)
    held = f"held-out RMS {np.sqrt(before.mean()):.3f} → {np.sqrt(after.mean()):.3f} µT"
    return better, held + (" (better on unseen blocks)" if better else " (not better beyond chance on unseen blocks)")


def judge(m_ut, t_s, channels, found, table: dict[str, Effect], model: str,
          known=()) -> tuple[np.ndarray, tuple[Verdict, ...]]:
    """(the samples with every kept effect removed, a verdict per located effect of kind
    PHYSICS); effects without a ``remove`` are judged not modelled. ``known`` as ``fitted``
    takes it (a list gets the fits made here: the one of the samples returned among them)."""
    base = heldout_sq(m_ut, model, known=known)
    verdicts = []
    for loc in sorted((f for f in found if f.kind is Kind.PHYSICS), key=_size, reverse=True):
        effect = table.get(loc.effect)
        if base is None or effect is None or effect.remove is None:
            verdicts.append(Verdict(loc, False, np.nan, np.nan, "no model of this effect to refit"))
            continue
        cleaned = effect.remove(m_ut, t_s, channels, loc)
        after = heldout_sq(cleaned, model, known=known)
        if after is None:
            verdicts.append(Verdict(loc, False, _rms(base), np.nan, "the calibration could not be refitted with it"))
            continue
        kept, why = compare(base, after)
        verdicts.append(Verdict(loc, kept, _rms(base), _rms(after), why))
        if kept:
            m_ut, base = cleaned, after
    return m_ut, tuple(verdicts)


def _rms(sq: np.ndarray) -> float:
    return float(np.sqrt(np.mean(sq)))


def _size(loc: Located) -> float:
    return float(loc.evidence.get("size_ut", 0.0) or 0.0)
