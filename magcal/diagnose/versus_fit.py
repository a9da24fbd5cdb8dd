"""Diagnosis's calibration against ``magcal fit --model auto`` on held-out time blocks.

The recording's valid samples, in time order, are cut into contiguous blocks. For each block,
both procedures are refitted on the other blocks and judged on it:

* ``fit``: ``fit_calibration(model="auto")`` on the training samples, as the command runs it
  (its own outlier removal, model choice by BIC and direction balance);
* ``diagnose``: the calibration refitted on the training samples the way ``diagnose`` made it
  for the whole recording (magcal.diagnose.heldout.choose_calibration): fit's own when that is
  what it returned (then both sides are the same); fit's, on the samples with the channel terms
  taken out, plus those terms (least squares) when it added channel terms; its own model shape
  by least squares when fit found none.

Both are judged the same way on the block's samples that diagnosis did not flag as glitches:
the relative radial error |h|/r − 1 of the calibrated field, times the field of a fit on the
whole recording (µT). Returns the RMS over all blocks for each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.calibration import Calibration
from ..fit import fit_calibration
from .channels import TIME
from .diagnosis import CalibrationSource
from .inference import contiguous_blocks
from .model import fit_model


@dataclass(frozen=True)
class Versus:
    diagnose_rms_ut: float
    fit_rms_ut: float
    blocks: int

    @property
    def never_worse(self) -> bool:
        return bool(self.diagnose_rms_ut <= self.fit_rms_ut * (1 + 1e-6))


def _relative_error(cal: Calibration, m: np.ndarray, chans: dict) -> np.ndarray:
    h = cal.correct(m, chans)
    return np.linalg.norm(h, axis=1) / cal.field_ut - 1.0


def _like_diagnose(source: CalibrationSource | None, model, m, chans, train, keep, fit_f) -> Calibration | None:
    """The calibration ``diagnose`` would return from the training samples alone (``source``
    None: one the locate step changed, judged as fit's geometry with diagnosis's terms)."""
    if source is CalibrationSource.FIT:
        return fit_f.calibration if fit_f else None
    kept = train & keep
    refit = fit_model(m[kept], {c: v[kept] for c, v in chans.items()}, model.spec, model.reference, start=model)
    if not refit:
        return None
    if source is CalibrationSource.DIAGNOSE:
        return refit.calibration()
    with_terms = refit.calibration()
    shift = with_terms.channel_offset_ut({c: v[train] for c, v in chans.items()}, int(train.sum()))
    geometry = fit_calibration(m[train] - shift, model="auto")
    if not geometry:
        return None
    g = geometry.calibration
    return Calibration(g.offset_ut, g.field_ut, g.soft_iron, with_terms.coef_ut_per_unit, with_terms.reference)


def heldout_versus_fit(diagnosis, folds: int = 5) -> Versus | None:
    """Both procedures on ``folds`` contiguous held-out blocks of the recording ``diagnosis``
    was made from (its ``series``); None when fit finds no model on the whole recording."""
    s = diagnosis.series
    m, t = s.field_ut, s.t_s
    chans = dict(s.channels)
    chans[TIME] = t
    keep = ~diagnosis.outlier_mask
    whole = fit_calibration(m, model="auto")
    if not whole:
        return None
    model = diagnosis.final
    sq_d = sq_f = 0.0
    n_eval = 0
    for held in contiguous_blocks(len(m), folds):
        train = np.ones(len(m), bool)
        train[held] = False
        test = ~train & keep
        fit_f = fit_calibration(m[train], model="auto")
        source = None if diagnosis.calibration_located else diagnosis.calibration_from
        cal_d = _like_diagnose(source, model, m, chans, train, keep, fit_f)
        if not fit_f or cal_d is None or not test.any():
            continue
        test_chans = {c: v[test] for c, v in chans.items()}
        err_d = _relative_error(cal_d, m[test], test_chans)
        err_f = _relative_error(fit_f.calibration, m[test], {})
        sq_d += float(err_d @ err_d)
        sq_f += float(err_f @ err_f)
        n_eval += int(test.sum())
    if not n_eval:
        return None
    scale = whole.calibration.field_ut
    return Versus(scale * np.sqrt(sq_d / n_eval), scale * np.sqrt(sq_f / n_eval), folds)
