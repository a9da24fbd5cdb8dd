"""The diagnosis's locate step: search the calibrated residual, judge, and model what earns it.

``locate_and_model`` builds the ``Residual`` of the calibration the diagnosis chose, runs every
row of ``EFFECTS`` on it, keeps each named effect only where removing it improves time-blocked
held-out prediction (``judge``), and refits the calibration on the samples with the kept
effects removed — the calibration in force at the end of the recording, which is what ``write``
puts on the device. Channel terms the diagnosis already found stay as they are, except where a
located term on the same channel (a lag, a gain, a curve) earns its place: that term *replaces*
the calibration's own no-lag term on the channel — in what is judged, in the refit and in the
findings (``replaced``: one finding per channel) — rather than being taken out on top of it,
which would take the channel's field out twice.
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
    replaced: tuple[str, ...] = ()  # channels whose no-lag calibration term a kept located term replaced

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
                     effects: tuple[Effect, ...], known: tuple = (), clock: bool = True) -> LocateStep:
    """See the module docstring. ``m_ut``/``t_s``/``chans`` the analysed samples that are not
    glitches (time order; ``chans`` the logged channels), ``final`` the model the diagnosis
    returns and ``fit_model_name`` the shape magcal fit chose for it; ``known``: fit's runs the
    diagnosis already made, as ``judge.fitted`` takes them; ``clock`` false where t_s is the
    sample index (``Series.clock``)."""
    cal = final.calibration()
    shift = cal.channel_offset_ut(chans, len(m_ut))
    floor = floor_of(m_ut - shift, known)
    res = Residual(t_s, m_ut, cal, noise_ut, floor, chans, clock)
    found = search(res, effects)
    if not any(f.kind is Kind.PHYSICS for f in found):
        return LocateStep(found, (), None, floor)
    model = PLAIN.get(fit_model_name, "auto")
    table = {e.name: replacing(e, cal, chans) for e in effects}
    cleaned, verdicts = judge.judge(m_ut - shift, t_s, chans, found, table, model, known)
    if not any(v.kept for v in verdicts):
        return LocateStep(found, verdicts, None, floor)
    replaced = tuple(sorted({str(v.located.params.get("channel")) for v in verdicts if v.kept} & set(cal.coef_ut_per_unit)))
    refit = _refit(cleaned, final, model, replaced)
    plain = {e.name: e for e in effects}  # the returned model carries no term on a replaced channel
    removals = tuple((plain[v.located.effect].remove, v.located) for v in verdicts if v.kept)
    if refit is None:
        return LocateStep(found, verdicts, None, floor, None, removals)
    in_force = cleaned + refit.calibration().channel_offset_ut(chans, len(m_ut))
    return LocateStep(found, verdicts, refit, floor, in_force, removals, replaced)


def replacing(effect: Effect, cal, chans: dict) -> Effect:
    """``effect`` whose ``remove`` of a located channel term first puts back the calibration's
    own (no-lag) term on that channel: the located term was fitted to the channel's whole effect
    (``channel_forms.search``) and replaces that term rather than being taken out on top of it."""
    if effect.remove is None:
        return effect

    def remove(m_ut, t_s, channels, located):
        name = located.params.get("channel")
        coef = cal.coef_ut_per_unit.get(name) if name is not None else None
        if coef is not None and name in chans:
            m_ut = m_ut + np.outer(np.asarray(chans[name], np.float64) - cal.reference.get(name, 0.0), coef)
        return effect.remove(m_ut, t_s, channels, located)

    return replace(effect, remove=remove)


def _refit(cleaned: np.ndarray, final: ModelFit, model: str, replaced: tuple = ()) -> ModelFit | None:
    """The geometry refitted on the cleaned samples, with ``final``'s channel terms kept except
    those a kept located term ``replaced``."""
    result = fit_calibration(cleaned, model=model, reasons=False)
    if not result:
        return None
    kept = tuple(c for c in final.spec.channels if c not in replaced)
    covs = {c: _channel_cov(final, j) for j, c in enumerate(final.spec.channels) if c in kept}
    geometry = from_calibration(result.calibration, result.model, result.n_used, result.rms_ut, result.uncertainty, covs)
    if not kept:
        return geometry
    spec = replace(geometry.spec, channels=kept)
    params = np.concatenate([geometry.params] + [final.coef_ut_per_unit[c] for c in kept])
    return ModelFit(spec, params, {c: final.reference[c] for c in kept}, geometry.rms_ut, geometry.n, 0, geometry.cov)


def _channel_cov(final: ModelFit, j: int) -> np.ndarray | None:
    """The 3×3 covariance of ``final``'s j-th channel term (None where it has none)."""
    if final.cov is None:
        return None
    k = 4 + final.spec.n_soft + 3 * j
    return final.cov[k : k + 3, k : k + 3]
