"""Step 7 of the diagnosis ladder: the calibration a diagnosis returns, never worse than
``magcal fit --model auto`` on contiguous held-out time blocks.

``choose_calibration`` compares the baseline, diagnosis's model (fit's geometry with the
channel terms added) and fit's own plain model, each refitted without each block and judged on
it (``compare_heldout``), and returns fit's calibration with a limit (``never_worse``) where
the channel terms did not help on unseen data. ``a`` is the ladder's ``Analysed`` samples
(magcal.diagnose.ladder): the analysed field ``m``, its channels ``chans`` and ``keep``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..fit import fit_calibration, fit_models
from .diagnosis import CalibrationSource, model_name
from .limits import Limit
from .locate import step as locate_step
from .model import ModelFit, fit_model, from_calibration


@dataclass(frozen=True)
class HeldOut:
    """Each model refitted without each contiguous time block and judged on it."""

    rms_ut: tuple  # per model, over every held-out block (glitches excluded)
    per_block: tuple  # per block: per model RMS
    fits: tuple = ()  # fit's runs on the blocks' training samples: (model, samples, result) (locate.judge.fitted)


def compare_heldout(a, models: list, fold_slices: list, procedure: int | None = None, also=()) -> HeldOut:
    """``models`` (None entries skipped) refitted on the kept samples outside each contiguous
    time block, from those samples alone, and judged on the block's kept samples. The entry at
    ``procedure`` stands for ``magcal fit --model auto`` and is judged as the procedure it is:
    fit runs again on each block's training samples, its gates and model choice included (its
    model refitted alone, the choice made with the held-out block in hand, would be judged on a
    shape fit may refuse without that block); where fit finds no model there, the model is
    refitted as the others are; fit's models ``also`` beside it, for the locate step (``fits``)."""
    sse = np.zeros(len(models))
    n_eval = 0
    per_block, known = [], []
    for held in fold_slices:
        train = np.ones(len(a.m), bool)
        train[held] = False
        train &= a.keep
        test = ~train & a.keep
        test[: held.start] = test[held.stop :] = False
        chans_train = {c: v[train] for c, v in a.chans.items()}
        chans_test = {c: v[test] for c, v in a.chans.items()}
        fits = [None if m is None else _refit_without(a.m[train], chans_train, m, i == procedure, known, also)
                for i, m in enumerate(models)]
        if not test.any() or any(m is not None and not f for m, f in zip(models, fits)):
            continue
        res = [f.residual(a.m[test], chans_test) if f else np.zeros(int(test.sum())) for f in fits]
        sse += [r @ r for r in res]
        n_eval += int(test.sum())
        per_block.append(tuple(float(np.sqrt(np.mean(r**2))) for r in res))
    rms = tuple(float(np.sqrt(v / n_eval)) if n_eval else float("nan") for v in sse)
    return HeldOut(tuple(r if m is not None else float("nan") for r, m in zip(rms, models)), tuple(per_block),
                   tuple(known))


def _refit_without(m_train: np.ndarray, chans_train: dict, model: ModelFit, as_fit: bool, known: list, also=()):
    """``model`` refitted on a block's training samples (``compare_heldout``); fit's run, when
    it is the procedure, added to ``known`` as (model, samples, result), and its models ``also``.
    Every other model — and the procedure's where fit finds none — is fitted by least squares
    from a start those samples give (the algebraic sphere), never from its full-data values: where
    the training samples leave the sphere open (a cap of directions), a short descent from the
    full-data values kept what the held-out block itself had pinned (notebook § The held-out
    blocks judged the baseline with the block's own information)."""
    if as_fit:
        results = fit_models(m_train, ("auto", *also))
        known.extend((k, m_train, r) for k, r in results.items())
        result = results["auto"]
        if result:
            return from_calibration(result.calibration, result.model, result.n_used, result.rms_ut)
    return fit_model(m_train, chans_train, model.spec, model.reference)


@dataclass(frozen=True)
class Chosen:
    """The calibration diagnosis returns, and how it did on the held-out blocks."""

    model: ModelFit
    source: CalibrationSource
    heldout: HeldOut  # baseline, the calibration returned, fit's plain model when it was compared
    limits: tuple[Limit, ...]  # why magcal fit's calibration was returned instead of diagnosis's (never_worse), if it was
    fit_model: str = "auto"  # the shape magcal fit chose ("sphere", "ellipsoid", …; "auto" when it found none)
    known: tuple = ()  # fit's runs on the way: (model, samples, result), for the locate step (locate.judge.fitted)

    @property
    def heldout_rms_ut(self) -> float:
        return self.heldout.rms_ut[2] if self.source is CalibrationSource.FIT and self.limits else self.heldout.rms_ut[1]

    @property
    def fit_heldout_rms_ut(self) -> float:
        return self.heldout.rms_ut[2] if np.isfinite(self.heldout.rms_ut[2]) else self.heldout.rms_ut[1]

    @property
    def fold_rms(self) -> tuple:
        col = 2 if self.source is CalibrationSource.FIT and self.limits else 1
        return tuple((b[0], b[col]) for b in self.heldout.per_block)


def choose_calibration(a, baseline: ModelFit, final: ModelFit, fold_slices: list, channel_cov: dict) -> Chosen:
    """Never worse than ``magcal fit --model auto``: its calibration (outlier removal, model
    choice by BIC, direction balance) is the geometry returned; diagnosis adds its channel terms
    to it, fitted the same way on the samples with those terms taken out — and only when that
    does better on the held-out blocks than the fit alone; otherwise a limit says so."""
    results = fit_models(a.m, ("auto", "ellipsoid"))  # the ellipsoid: the locate step's floor
    result = results["auto"]
    whole = tuple((k, a.m, r) for k, r in results.items())
    if not result:
        return Chosen(final, CalibrationSource.DIAGNOSE, compare_heldout(a, [baseline, final, None], fold_slices), (), known=whole)
    also = tuple({locate_step.PLAIN.get(result.model)} - {None})  # the model the locate step's judge refits
    plain = from_calibration(result.calibration, result.model, result.n_used, result.rms_ut, result.uncertainty)
    if not final.spec.channels:
        heldout = compare_heldout(a, [baseline, plain, None], fold_slices, procedure=1, also=also)
        return Chosen(plain, CalibrationSource.FIT, heldout, (), result.model, whole + heldout.fits)
    geometry, shifted = _fit_geometry_around_channels(a, final, channel_cov, result.model)
    with_channels = geometry or final
    heldout = compare_heldout(a, [baseline, with_channels, plain], fold_slices, procedure=2, also=also)
    limit = never_worse(with_channels, plain, heldout)
    known = whole + (shifted,) + heldout.fits
    if limit:
        return Chosen(plain, CalibrationSource.FIT, heldout, (limit,), result.model, known)
    return Chosen(with_channels, CalibrationSource.FIT_CHANNELS, heldout, (), result.model, known)


def _fit_geometry_around_channels(a, final: ModelFit, channel_cov: dict,
                                  chosen: str) -> tuple[ModelFit | None, tuple]:
    """Offset, soft iron and radius as magcal fit finds them once ``final``'s channel terms
    are taken out of every analysed sample, with the model fit chose on the samples as they
    are (``chosen``: its name; the sphere or the full ellipsoid are fitted alone, the diagonal
    one by fit's own choice again); the channel terms kept as they are. With it, fit's run as
    (model, samples, result) (locate.judge.fitted)."""
    shift = final.calibration().channel_offset_ut(a.chans, len(a.m))
    model, samples = {"sphere": "sphere", "ellipsoid": "ellipsoid"}.get(chosen, "auto"), a.m - shift
    result = fit_calibration(samples, model=model, reasons=False)
    if not result:
        return None, (model, samples, result)
    covs = {c: channel_cov.get(c) for c in final.spec.channels}
    geometry = from_calibration(result.calibration, result.model, result.n_used, result.rms_ut, result.uncertainty, covs)
    spec = replace(geometry.spec, channels=final.spec.channels)
    params = np.concatenate([geometry.params] + [final.coef_ut_per_unit[c] for c in final.spec.channels])
    return ModelFit(spec, params, dict(final.reference), geometry.rms_ut, geometry.n, 0, geometry.cov), \
        (model, samples, result)


def never_worse(own: ModelFit, fit_auto: ModelFit, heldout: HeldOut) -> Limit | None:
    """When the fit's plain model does better on the held-out blocks than diagnosis's, a limit
    saying so (the fit's calibration is then the one returned); None otherwise."""
    mine, theirs = heldout.rms_ut[1], heldout.rms_ut[2]
    if not (np.isfinite(mine) and np.isfinite(theirs)) or mine <= theirs * (1 + 1e-9):
        return None
    return Limit(
        "calibration",
        False,
        f"On held-out stretches of the recording the calibration of magcal fit --model auto "
        f"({model_name(fit_auto)}) leaves {theirs:.3f} µT against {mine:.3f} µT with diagnosis's channel terms "
        f"added ({model_name(own)}), so the fit's calibration is the one returned; the findings stand as "
        "evidence, but what they add did not improve unseen data here.",
        details={"heldout_rms_ut_diagnosis": mine, "heldout_rms_ut_fit": theirs},
    )
