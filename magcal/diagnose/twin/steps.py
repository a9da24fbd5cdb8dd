"""The comparison step by step (``compare_steps``): the baseline (hard iron + white noise),
then the model with each effect it carries added in turn, ending at the learned model — each
step compared with the recording on the same seeds.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...core.calibration import Calibration
from ...core.series import Series
from ...fit.sphere import fit_sphere
from ...sim import directions
from ...sim.model import SensorModel
from .comparison import BAND, DRAWS, StepComparison, compare
from .residual import refit, with_time


ORDER = ("calibration", "quantum", "wander", "field_wander", "nonlinearity", "temperature_gain", "glitches",
         "disturbances", "saturation", "repeats", "noise_law")
_LATER = {step: ORDER[i + 1:] for i, step in enumerate(ORDER)}  # what a step still leaves out


@dataclass(frozen=True)
class TwinReport:
    """The comparison of each step, baseline first, the learned model last."""

    model: SensorModel
    steps: tuple

    @property
    def final(self) -> StepComparison:
        return self.steps[-1]

    @property
    def baseline(self) -> StepComparison:
        return self.steps[0]

    def to_dict(self) -> dict:
        return {"version": 1, "draws": self.final.draws, "band_pct": list(BAND),
                "steps": [c.to_dict() for c in self.steps], "model": self.model.to_dict()}


def baseline_model(model: SensorModel, series: Series, free: bool = True) -> SensorModel:
    """Hard iron + white noise: the sphere fitted to the recording (or, when the recording
    cannot determine one, the model's offset and field), its RMS as the noise."""
    m = series.only_valid().field_ut
    f = fit_sphere(m) if free else None
    if free and not f:
        raise ValueError(f"cannot fit the baseline sphere: {f}")
    if f:
        cal, rms = Calibration(offset_ut=f.offset_ut, field_ut=f.field_ut), f.rms_ut
    else:
        cal = Calibration(offset_ut=model.calibration.offset_ut, field_ut=model.calibration.field_ut)
        r = np.linalg.norm(m - cal.offset_ut, axis=1)
        rms = float(np.std(r))
    return SensorModel(calibration=cal, noise_ut=(rms,) * 3, rate_hz=model.rate_hz)


def whitened(model: SensorModel, series: Series, free: bool = True) -> SensorModel:
    """``model`` with its noise raised to carry all of the residual a model without wander
    leaves (so the step is judged on its shape, not on a missing variance)."""
    s = series.only_valid()
    real = refit(model, s.field_ut, s.t_s, with_time(s), free)
    if real is None:
        return model
    quant = float(np.mean(real.u**2 @ (np.asarray(model.quantum_ut) ** 2 / 12.0)))
    extra = float(np.var(real.e)) - quant - float(np.mean(directions.radial_ut(real.u, model.nonlinearity_ut) ** 2))
    return replace(model, noise_ut=(float(np.sqrt(max(extra, 1e-12))),) * 3)


def step_models(model: SensorModel, series: Series, free: bool = True) -> list[tuple[str, SensorModel]]:
    """(name, model) from the baseline through each effect the learned model carries."""
    has = set(model.effects()) | ({"quantum"} if any(model.quantum_ut) else set())
    out = [("baseline", baseline_model(model, series, free))]
    for step in ORDER:
        present = has & {"soft_iron", "takes", *model.calibration.coef_ut_per_unit} if step == "calibration" else has & {step}
        if not present:
            continue
        m = model
        for later in _LATER[step]:
            if later in has:
                m = m.without(later)
        if not {"wander", "field_wander"} & set(m.effects()):
            m = whitened(m, series, free)
        out.append(("+" + step if _LATER[step] and any(x in has for x in _LATER[step]) else "final", m))
    if out[-1][0] != "final":
        out.append(("final", model))
    return out


def compare_steps(model: SensorModel, series: Series, draws: int = DRAWS, seed: int = 0, free: bool = True,
                  on_step=None) -> TwinReport:
    """Compare each step with the recording on the same seeds; ``on_step(i, n, name)`` is
    called as step ``i`` of ``n`` begins (steps of like cost: a display's stage and ETA)."""
    models = step_models(model, series, free)
    steps = []
    for i, (name, m) in enumerate(models):
        if on_step is not None:
            on_step(i, len(models), name)
        steps.append(compare(m, series, draws, seed, name, free))
    return TwinReport(model=model, steps=tuple(steps))
