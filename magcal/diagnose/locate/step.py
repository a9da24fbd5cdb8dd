"""The diagnosis's locate step: search the calibrated residual, judge, and model what earns it.

``locate_and_model`` builds the ``Residual`` of the calibration the diagnosis chose, runs every
row of ``EFFECTS`` on it, keeps each named effect only where removing it improves time-blocked
held-out prediction (``judge``), and refits the calibration on the samples with the kept
effects removed — the calibration in force at the end of the recording, which is what ``write``
puts on the device. Channel terms the diagnosis already found stay as they are.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...fit import fit_calibration
from ..model import ModelFit, from_calibration
from . import judge
from .base import Effect, Kind, Located, Residual

PLAIN = {"sphere": "sphere", "ellipsoid": "ellipsoid"}


@dataclass(frozen=True)
class LocateStep:
    """What the step found and did: every located thing, the verdict on each named effect,
    and the model to return (None: the diagnosis's own stands)."""

    found: tuple[Located, ...]
    verdicts: tuple[judge.Verdict, ...]
    model: ModelFit | None
    floor_ut: float
    cleaned_ut: np.ndarray | None = None  # the samples with every modelled effect removed (with ``model``)
    removals: tuple = ()  # (remove, located) of each modelled effect, in the order it was removed

    def modelled(self, m_ut: np.ndarray, t_s: np.ndarray, chans: dict) -> np.ndarray:
        """Any samples of the recording with the modelled effects removed, as the returned
        calibration sees them (the samples as they are when nothing was modelled)."""
        if self.model is None:
            return m_ut
        shift = self.model.calibration().channel_offset_ut(chans, len(m_ut))
        out = m_ut - shift
        for remove, loc in self.removals:
            out = remove(out, t_s, chans, loc)
        return out + shift

    @property
    def heldout_rms_ut(self) -> float:
        """The held-out RMS of the calibration returned with the modelled effects (nan: none)."""
        kept = [v for v in self.verdicts if v.kept]
        return kept[-1].heldout_with_ut if kept else float("nan")

    @property
    def kept(self) -> tuple[Located, ...]:
        return tuple(v.located for v in self.verdicts if v.kept)


def floor_of(m_ut: np.ndarray, known: tuple = ()) -> float:
    """The recording's own floor: the RMS radial residual of a plain ellipsoid (nan where none
    fits); ``known`` as ``judge.fitted`` takes it."""
    result = judge.fitted(m_ut, "ellipsoid", known)
    return float(result.rms_ut) if result else float("nan")


MAX_EMPTY_TIME = 8.0  # a time axis this many times longer than its samples at their own interval is mostly gap


def search(res: Residual, effects: tuple[Effect, ...]) -> tuple[Located, ...]:
    """Every non-fault row of the table on one residual; none where the time axis is mostly
    empty (a timestamp from far away in a damaged log: every locator reads time, and a grid over
    such a span is no search)."""
    t = np.asarray(res.t_s, float)
    steps = np.diff(t)[np.diff(t) > 0]  # a coarse clock repeats times: its ticks are the interval
    if not len(steps) or float(t[-1] - t[0]) > MAX_EMPTY_TIME * len(t) * float(np.median(steps)):
        return ()
    return tuple(x for e in effects if e.kind is not Kind.FAULT for x in e.search(res))


def locate_and_model(m_ut, t_s, chans: dict, final: ModelFit, fit_model_name: str, noise_ut: float,
                     effects: tuple[Effect, ...], known: tuple = ()) -> LocateStep:
    """See the module docstring. ``m_ut``/``t_s``/``chans`` the analysed samples that are not
    glitches (time order; ``chans`` the logged channels), ``final`` the model the diagnosis
    returns and ``fit_model_name`` the shape magcal fit chose for it; ``known``: fit's runs the
    diagnosis already made, as ``judge.fitted`` takes them."""
    cal = final.calibration()
    shift = cal.channel_offset_ut(chans, len(m_ut))
    floor = floor_of(m_ut - shift, known)
    res = Residual(t_s, m_ut, cal, noise_ut, floor, chans)
    found = search(res, effects)
    if not any(f.kind is Kind.PHYSICS for f in found):
        return LocateStep(found, (), None, floor)
    model = PLAIN.get(fit_model_name, "auto")
    table = {e.name: e for e in effects}
    cleaned, verdicts = judge.judge(m_ut - shift, t_s, chans, found, table, model, known)
    if not any(v.kept for v in verdicts):
        return LocateStep(found, verdicts, None, floor)
    refit = _refit(cleaned, final, model)
    removals = tuple((table[v.located.effect].remove, v.located) for v in verdicts if v.kept)
    return LocateStep(found, verdicts, refit, floor, None if refit is None else cleaned + shift, removals)


def _refit(cleaned: np.ndarray, final: ModelFit, model: str) -> ModelFit | None:
    """The geometry refitted on the cleaned samples, with ``final``'s channel terms kept."""
    result = fit_calibration(cleaned, model=model)
    if not result:
        return None
    covs = {c: _channel_cov(final, j) for j, c in enumerate(final.spec.channels)}
    geometry = from_calibration(result.calibration, result.model, result.n_used, result.rms_ut, result.uncertainty, covs)
    if not final.spec.channels:
        return geometry
    spec = replace(geometry.spec, channels=final.spec.channels)
    params = np.concatenate([geometry.params] + [final.coef_ut_per_unit[c] for c in final.spec.channels])
    return ModelFit(spec, params, dict(final.reference), geometry.rms_ut, geometry.n, 0, geometry.cov)


def _channel_cov(final: ModelFit, j: int) -> np.ndarray | None:
    """The 3×3 covariance of ``final``'s j-th channel term (None where it has none)."""
    if final.cov is None:
        return None
    k = 4 + final.spec.n_soft + 3 * j
    return final.cov[k : k + 3, k : k + 3]
