"""Diagnosis: what ``diagnose`` returns, as a value (the JSON shape of ``magcal diagnose``)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from ..core.calibration import Calibration
from ..core.series import Series
from . import channels
from .finding import Finding
from .limits import Limit
from .model import ModelFit


class CalibrationSource(str, Enum):
    """Where the calibration a diagnosis returns came from (heldout.choose_calibration); its
    value is the JSON's ``final.from`` (with ``+located`` where the locate step changed it)."""

    FIT = "fit"  # magcal fit --model auto's own
    FIT_CHANNELS = "fit+channels"  # fit's shape and estimator with diagnosis's channel terms
    DIAGNOSE = "diagnose"  # diagnosis's own model (fit found none)


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def model_name(fit: ModelFit) -> str:
    """"sphere" or "ellipsoid", then each channel term: ``ellipsoid+temp_c``."""
    parts = ["ellipsoid" if fit.spec.soft_iron else "sphere"]
    parts += [f"{c}" for c in fit.spec.channels]
    return "+".join(parts)


def reported_calibration(fit: ModelFit) -> Calibration:
    """``fit``'s calibration in fit's convention (``magcal.fit``: det W = 1, the radius with it):
    the one the JSON holds and ``magcal write`` puts on a device, so that the calibration
    diagnosis takes from fit has fit's numbers; the model's own scale (trace W = 3) only rescales
    the calibrated field, and both W and the radius by the same factor."""
    cal = fit.calibration()
    det = float(np.linalg.det(np.asarray(cal.soft_iron, np.float64)))
    scale = det ** (-1.0 / 3.0) if np.isfinite(det) and det > 0 else 1.0
    return replace(cal, field_ut=cal.field_ut * scale, soft_iron=np.asarray(cal.soft_iron) * scale)


def calibration_dict(fit: ModelFit) -> dict:
    """The ``calibration`` object of the JSON (``reported_calibration``)."""
    cal = reported_calibration(fit)
    reference = {channels.TEMP: float(cal.reference.get(channels.TEMP, 0.0)), channels.CURRENT: 0.0}
    reference.update({k: float(v) for k, v in cal.reference.items()})
    if channels.TEMP not in cal.reference:
        reference.pop(channels.TEMP)
    out = {
        "offset_ut": [float(v) for v in cal.offset_ut],
        "field_ut": float(cal.field_ut),
        "soft_iron": [[float(v) for v in row] for row in cal.soft_iron],
        "reference": reference,
    }
    if cal.coef_ut_per_unit:
        out["coef_ut_per_unit"] = {k: [float(x) for x in v] for k, v in cal.coef_ut_per_unit.items()}
    return out


@dataclass(frozen=True)
class Diagnosis:
    n_samples: int
    baseline: ModelFit
    final: ModelFit
    findings: tuple[Finding, ...]
    baseline_heldout_rms_ut: float
    final_heldout_rms_ut: float
    simulated_rms_ut: float
    noise_ut: float
    series: Series = field(repr=False)  # the analysed samples (valid, finite)
    outlier_mask: np.ndarray = field(repr=False)
    tests: dict = field(default_factory=dict, repr=False)
    folds: tuple = field(default=(), repr=False)
    fold_rms: tuple = field(default=(), repr=False)  # ((baseline, final) per fold)
    limits: tuple[Limit, ...] = ()  # what this recording could not test, and whether it is suspected
    floors: dict = field(default_factory=dict)  # channel → the size a term of it must reach to be reported
    fit_heldout_rms_ut: float = float("nan")  # magcal fit --model auto's model on the same held-out blocks
    diagnosis_model: ModelFit | None = field(default=None, repr=False)  # diagnosis's own least-squares model
    calibration_from: CalibrationSource = CalibrationSource.DIAGNOSE  # see heldout.choose_calibration
    calibration_located: bool = False  # effects the locate step modelled changed it
    located: object = field(default=None, repr=False)  # the locate step (magcal.diagnose.locate.step.LocateStep)

    @property
    def effects(self) -> list[str]:
        return [f.effect for f in self.findings]

    def model_name(self, fit: ModelFit) -> str:
        return model_name(fit)

    def modelled_field_ut(self) -> np.ndarray:
        """The analysed samples as the returned calibration takes them: with the effects the
        locate step modelled removed (a hard-iron step, a line …); as recorded otherwise."""
        s = self.series
        if self.located is None:
            return s.field_ut
        return self.located.modelled(s.field_ut, s.t_s, {**s.channels, channels.TIME: s.t_s})

    def _located_dict(self) -> dict:
        """What the locate step searched and found: the recording's floor, every located thing
        with its ``where``, and the held-out verdict on each named effect."""
        step = self.located
        if step is None:
            return {"floor_ut": None, "found": [], "verdicts": []}
        return {
            "floor_ut": _num(step.floor_ut),
            "found": [x.to_dict() for x in step.found],
            "verdicts": [{"effect": v.located.effect, **v.evidence()} for v in step.verdicts],
        }

    def to_dict(self) -> dict:
        return {
            "n_samples": int(self.n_samples),
            "baseline": {
                "model": "sphere",
                "rms_ut": float(self.baseline.rms_ut),
                "heldout_rms_ut": float(self.baseline_heldout_rms_ut),
            },
            "findings": [f.to_dict() for f in self.findings],
            "final": {
                "model": model_name(self.final),
                "rms_ut": float(self.final.rms_ut),
                "heldout_rms_ut": float(self.final_heldout_rms_ut),
                "simulated_rms_ut": float(self.simulated_rms_ut),
                "from": self.calibration_from.value + ("+located" if self.calibration_located else ""),
                "fit_heldout_rms_ut": _num(self.fit_heldout_rms_ut),
            },
            "noise_ut": float(self.noise_ut),
            "limits": [x.to_dict() for x in self.limits],
            "located": self._located_dict(),
            "floors": {c: dict(f) for c, f in self.floors.items()},
            "calibration": calibration_dict(self.final),
        }
