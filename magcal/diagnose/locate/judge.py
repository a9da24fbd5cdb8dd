"""Keep a located effect only where modelling it improves time-blocked held-out prediction.

Each named effect comes with its ``remove`` (``Effect.remove``): the samples with the effect
taken out. The calibration is refitted (``magcal fit``'s own procedure, with the model it chose)
on every contiguous time block's complement, with and without the effect removed, and judged on
the block it left out; an effect is kept when its held-out RMS radial residual is lower by more
than the scatter of that gain over the blocks allows to be chance. Effects are judged one after
another, largest first, each on the samples with the ones already kept taken out. An effect whose
search tested it against a simpler account of the same change (``Effect.simpler``: a soft-iron
change against the offset alone changing at its time) must beat that on unseen blocks too, and
is judged against it where it does not: a change of offset does not earn a change of shape.
Where the effect's own parameters can be refitted (``Effect.remove_trained``: a change point's
step vector, or each side's ellipsoid), the block scored helped fit it, and on a short window
whose coverage pins neither side that alone makes a change look better on "unseen" data; so a
kept effect is also scored with them fitted on each block's complement alone, and dropped where
that leaves unseen blocks worse than without it.

An effect not kept is still the honest remainder where it took something off unseen blocks —
unless what it took (the held-out gain as an RMS per reading, µT) is no more than the recording's
own noise and slow offset wander together (``base.noise_and_wander_ut``, measured on the samples
with the effect taken out and refitted, so what sizes it never holds the effect itself). That
much is the noise, and the ``offset_wander`` limit's to state ("a calibration from this
recording is good to about that much"); it is not also unexplained structure.

Nor is a gain carried by one or two of the ``FOLDS`` held-out blocks (``Verdict.spread``): the
remainder says the recording holds structure the located effect resembles, and a recording that
holds it shows it on most unseen blocks — the median block's gain beats the noise and slow wander.
A total carried by one block is what that block's own stretch did (a hand moving near iron, a
turn no other stretch repeats): where the recording was held and how far its coverage reaches,
not structure located in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...fit import fit_calibration
from ..inference import contiguous_blocks
from .base import Effect, Kind, Located, noise_and_wander_ut

FOLDS = 5
SIMPLER_WORDS = "the simpler account its search tested it against (Effect.simpler)"
MIN_GAIN_SIGMAS = 2.0  # the held-out gain must exceed this many standard errors of its block scatter


@dataclass(frozen=True)
class Verdict:
    """One effect judged on held-out blocks: RMS radial residual (µT) without and with it."""

    located: Located
    kept: bool
    heldout_without_ut: float
    heldout_with_ut: float
    reason: str
    wander_ut: float = float("nan")  # the slow wander left with it taken out (nan: not measured)
    noise_ut: float = float("nan")  # the noise of one reading, likewise
    block_gain_sq: tuple[float, ...] = ()  # per held-out block, mean square without minus with (µT²; empty: not measured)

    @property
    def contradicted(self) -> bool:
        """Modelling it made unseen blocks worse: the recording itself speaks against it."""
        return bool(self.heldout_with_ut >= self.heldout_without_ut)

    @property
    def gain_ut(self) -> float:
        """What modelling it took off unseen blocks, as an RMS (µT; 0 when nothing)."""
        return float(np.sqrt(max(self.heldout_without_ut**2 - self.heldout_with_ut**2, 0.0)))

    @property
    def within_noise_and_wander(self) -> bool:
        """Not kept, and what it took off unseen blocks is no more than the noise and slow wander
        the recording keeps without it: the noise, and the wander limit's to state — no remainder."""
        allowed = np.hypot(self.noise_ut, self.wander_ut)
        return bool(not self.kept and np.isfinite(allowed) and self.gain_ut <= allowed)

    @property
    def median_block_gain_ut(self) -> float:
        """What modelling it took off the median unseen block, as an RMS (µT; nan: not measured)."""
        if not self.block_gain_sq:
            return float("nan")
        return float(np.sqrt(max(float(np.median(self.block_gain_sq)), 0.0)))

    @property
    def spread(self) -> bool:
        """Its held-out gain is the recording's, not one or two blocks': the median block's gain
        beats the noise and slow wander left without it (true where the blocks were not measured)."""
        allowed = np.hypot(self.noise_ut, self.wander_ut)
        g = self.median_block_gain_ut
        return bool(not (np.isfinite(g) and np.isfinite(allowed)) or g > allowed)

    def evidence(self) -> dict:
        wander = ({"heldout_gain_ut": self.gain_ut, "noise_without_ut": self.noise_ut, "wander_without_ut": self.wander_ut,
                   "median_block_gain_ut": self.median_block_gain_ut}
                  if np.isfinite(self.wander_ut) else {})
        return {
            "heldout_rms_without_ut": self.heldout_without_ut,
            "heldout_rms_with_ut": self.heldout_with_ut,
            "modelled": self.kept,
            "why": self.reason,
            **wander,
        }


def fitted(m_ut: np.ndarray, model: str, known: tuple = ()):
    """``fit_calibration(m_ut, model=model)``; ``known``: fit's runs already made, as (model,
    samples, result), one of which is taken where it was made with this model on these very
    samples (the diagnosis runs fit on the same samples as the locate step at times: a block's
    complement when nothing was set aside, the samples with its channel terms out)."""
    for k_model, samples, result in known:
        if k_model == model and samples.shape == m_ut.shape and np.array_equal(samples, m_ut):
            return result
    return fit_calibration(m_ut, model=model, reasons=False)


def heldout_sq(m_ut: np.ndarray, model: str, folds: int = FOLDS, known: tuple = ()) -> np.ndarray | None:
    """Per block, the mean square radial residual of the calibration refitted without that
    block; None where a block's complement cannot be fitted. ``known`` as ``fitted`` takes it."""
    return _block_sq(lambda train: m_ut, len(m_ut), model, folds, known)


def _block_sq(samples_for, n: int, model: str, folds: int, known: tuple = ()) -> np.ndarray | None:
    """Per contiguous block of ``n`` samples, the mean square radial residual of that block
    under the calibration refitted on the rest, the samples being ``samples_for(train)`` (the
    training mask); None where a block's complement cannot be fitted."""
    out = []
    for held in contiguous_blocks(n, folds):
        train = np.ones(n, bool)
        train[held] = False
        m_ut = samples_for(train)
        result = fitted(m_ut[train], model, known)
        if not result:
            return None
        cal = result.calibration
        r = np.linalg.norm(cal.correct(m_ut[held]), axis=1) - cal.field_ut
        out.append(float(np.mean(r**2)))
    return np.asarray(out)


def compare(before: np.ndarray, after: np.ndarray) -> tuple[bool, str]:
    """Whether the per-block mean squares ``after`` beat ``before`` beyond chance."""
    gain = before - after
    se = np.std(gain, ddof=1) / np.sqrt(len(gain)) if len(gain) > 1 else np.inf
    better = bool(gain.mean() > MIN_GAIN_SIGMAS * se and gain.mean() > 0)
    held = f"held-out RMS {np.sqrt(before.mean()):.3f} → {np.sqrt(after.mean()):.3f} µT"
    return better, held + (" (better on unseen blocks)" if better else " (not better beyond chance on unseen blocks)")


def judge(m_ut, t_s, channels, found, table: dict[str, Effect], model: str,
          known: tuple = ()) -> tuple[np.ndarray, tuple[Verdict, ...]]:
    """(the samples with every kept effect removed, a verdict per located effect of kind
    PHYSICS); effects without a ``remove`` are judged not modelled. ``known`` as ``fitted``
    takes it."""
    base = heldout_sq(m_ut, model, known=known)
    verdicts = []
    for loc in sorted((f for f in found if f.kind is Kind.PHYSICS), key=_size, reverse=True):
        effect = table.get(loc.effect)
        if base is None or effect is None or effect.remove is None:
            verdicts.append(Verdict(loc, False, np.nan, np.nan, "no model of this effect to refit"))
            continue
        cleaned = effect.remove(m_ut, t_s, channels, loc)
        after = heldout_sq(cleaned, model)
        if after is None:
            verdicts.append(Verdict(loc, False, _rms(base), np.nan, "the calibration could not be refitted with it"))
            continue
        kept, why, without = _against_simpler(m_ut, t_s, channels, loc, effect, model, base, after)
        if kept and effect.remove_trained is not None:
            kept, why, without, after = _trained(m_ut, t_s, channels, loc, effect, model, base, (why, after))
        left = without_it(cleaned, model) if not kept and after.mean() < without.mean() else (np.nan, np.nan)
        verdicts.append(Verdict(loc, kept, _rms(without), _rms(after), why, left[1], left[0], tuple(map(float, without - after))))
        if kept:
            m_ut, base = cleaned, after
    return m_ut, tuple(verdicts)


def _against_simpler(m_ut, t_s, channels, loc, effect: Effect, model: str, base, after):
    """(kept, why, the held-out figures it was judged against): better than nothing beyond
    chance, and, where the effect has a simpler account (``Effect.simpler``), better than that
    too — else it is judged against the simpler account, which is what it must beat."""
    kept, why = compare(base, after)
    if not kept or effect.simpler is None:
        return kept, why, base
    simpler = heldout_sq(effect.simpler(m_ut, t_s, channels, loc), model)
    if simpler is None:
        return kept, why, base
    beats, why_simpler = compare(simpler, after)
    if beats:
        return True, why, base
    return False, f"{why}, but against {SIMPLER_WORDS}: {why_simpler}", simpler


def heldout_sq_trained(m_ut, t_s, channels, loc, remove_trained, model: str, folds: int = FOLDS) -> np.ndarray | None:
    """As ``heldout_sq`` on the samples with the effect removed, but with the effect's own
    parameters refitted on each block's complement (``Effect.remove_trained``): the block is
    scored by a change it did not help fit."""
    return _block_sq(lambda train: remove_trained(m_ut, t_s, channels, loc, train), len(m_ut), model, folds)


def _trained(m_ut, t_s, channels, loc, effect: Effect, model: str, base, judged):
    """(kept, why, the held-out figures without and with it): an effect kept so far is dropped
    where, with its parameters fitted on the training blocks alone, unseen blocks are worse with
    it than without (``Verdict.contradicted``, judged by those figures). Not "beyond chance"
    again: a block whose complement holds too little of one side cannot learn the change and
    gains nothing, so these figures are weaker evidence for it, though honest evidence against.
    ``judged``: (why, per-block figures with it) so far."""
    why, after = judged
    trained = heldout_sq_trained(m_ut, t_s, channels, loc, effect.remove_trained, model)
    if trained is None or trained.mean() < base.mean():
        return True, why, base, after
    words = f"held-out RMS {_rms(base):.3f} → {_rms(trained):.3f} µT"
    return False, f"{why}, but with its own parameters fitted on the training blocks alone: {words} (worse)", base, trained


def without_it(m_ut: np.ndarray, model: str) -> tuple[float, float]:
    """(noise, slow wander) of ``m_ut``'s radial residual around its own calibration
    (``base.noise_and_wander_ut``); nan where no calibration fits."""
    result = fit_calibration(m_ut, model=model, reasons=False)
    if not result:
        return float("nan"), float("nan")
    cal = result.calibration
    h = cal.correct(m_ut)
    norm = np.linalg.norm(h, axis=1)
    return noise_and_wander_ut(norm - cal.field_ut, h / norm[:, None])


def _rms(sq: np.ndarray) -> float:
    return float(np.sqrt(np.mean(sq)))


def _size(loc: Located) -> float:
    return float(loc.evidence.get("size_ut", 0.0) or 0.0)
