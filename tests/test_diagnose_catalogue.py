"""The design is its table: design.build makes one group of columns per tested effect of the
table it is given, in the table's order, and an effect added to the table as a value is tested
like every other (magcal.diagnose.catalogue, design.CATALOGUE)."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.diagnose import channels, design, harmonics, ladder, softiron, wander
from magcal.diagnose.catalogue import CatalogueEffect, Columns, Role
from magcal.diagnose.finding import Finding
from magcal.diagnose.model import Spec, fit_model
from magcal.sim.physics import Current, Motion, Physics, Scenario, Temperature

HARD = np.array([21.0, -33.0, 8.0])
N = 3000


def _recording(seed: int, gain_per_a: float = 0.0):
    """A simulated recording with soft iron, a temperature and a current logged (60 s at 50 Hz),
    its field's gain raised by ``gain_per_a`` per ampere of the current."""
    phys = Physics(hard_iron_ut=tuple(HARD), distortion=((1.02, 0.0, 0.0), (0.0, 0.99, 0.0), (0.0, 0.0, 0.985)))
    run = Scenario(physics=phys, motion=Motion("sphere", period_s=10.0), temperature=Temperature(swing_c=15.0, period_s=20.0),
                   current=Current(level_a=2.0), seed=seed).simulate(N, 50.0)
    s = run.series
    m = HARD + (s.field_ut - HARD) * (1.0 + gain_per_a * s.channels[channels.CURRENT])[:, None]
    chans = dict(s.channels)
    candidates, _ = channels.candidates(s.t_s, chans)
    chans[channels.TIME] = s.t_s
    return m, s.t_s, chans, fit_model(m, {}, Spec(soft_iron=True)), candidates


def _current_gain_columns(lin) -> Columns:
    """One column: the radial residual a gain that follows the current leaves (|h| · current)."""
    return Columns((lin.reference.field_ut * lin.chans[channels.CURRENT])[:, None], (("current_gain", 1),))


def _current_gain_finding(acc) -> Finding:
    return Finding(effect="current_gain", summary="the gain follows the current", where={},
                   evidence=dict(acc.evidence), params={})


CURRENT_GAIN = CatalogueEffect("current_gain", Role.TESTED, _current_gain_columns, _current_gain_finding, 0.1)


def test_the_design_holds_each_effect_of_the_table_in_its_order():
    m, t, chans, ref, cands = _recording(5)
    dsg = design.build(m, t, chans, ref, cands)
    lin = design.linearise(m, t, chans, ref, cands)
    widths = [e.columns(lin).x.shape[1] for e in design.CATALOGUE]
    assert widths[0] == 4 and widths[1] == 5 and widths[2] == 3 * len(cands)  # offset + radius, soft iron, channels
    assert dsg.x.shape[1] == sum(widths)
    assert (dsg.n_jacobian, dsg.n_before_wander) == (widths[0], sum(widths[:-1]))
    assert list(dsg.groups) == [softiron.EFFECT, "temperature_drift", "current_interference", "time_drift"]
    order = np.concatenate(list(dsg.groups.values()))
    assert np.array_equal(order, np.arange(4, 4 + 5 + 3 * len(cands)))  # consecutive, in the table's order
    assert dsg.effects[softiron.EFFECT] is softiron.TERM and dsg.effects["current_interference"] is channels.TERM
    assert dsg.coverage_gates == {g: (softiron.MIN_UNIQUE if g == softiron.EFFECT else channels.MIN_UNIQUE)
                                  for g in dsg.groups}
    # a table without the direction harmonics gives a design without their columns, the groups unchanged
    lean = design.build(m, t, chans, ref, cands, catalogue=tuple(e for e in design.CATALOGUE if e is not harmonics.TERM))
    assert lean.x.shape[1] == dsg.x.shape[1] - widths[3]
    assert {g: list(c) for g, c in lean.groups.items()} == {g: list(c) for g, c in dsg.groups.items()}


def _with_current_gain(seed: int, gain_per_a: float):
    m, t, chans, ref, cands = _recording(seed, gain_per_a)
    table = (design.BASELINE, softiron.TERM, channels.TERM, CURRENT_GAIN, harmonics.TERM, wander.TERM)
    dsg = design.build(m, t, chans, ref, cands, catalogue=table)
    return dsg, ladder.tested_columns(dsg, True, None).test(dsg.groups)


def test_an_effect_added_to_the_table_is_its_own_group_and_is_tested():
    dsg, tests = _with_current_gain(5, 0.005)  # 1 % at 2 A: 0.5 µT of radius against 0.4 µT of noise
    after_channels = 4 + 5 + 3 * len(dsg.candidates)
    assert list(dsg.groups["current_gain"]) == [after_channels]
    assert dsg.effects["current_gain"] is CURRENT_GAIN and dsg.coverage_gates["current_gain"] == 0.1
    assert tests["current_gain"].p < 1e-4
    assert tests["current_gain"].beta[0] == pytest.approx(0.005, rel=0.2)  # its coefficient: the gain per ampere
    _, quiet = _with_current_gain(5, 0.0)  # the same recording without it
    assert quiet["current_gain"].p > 0.01


def test_a_table_out_of_column_order_or_naming_a_group_twice_is_refused():
    m, t, chans, ref, cands = _recording(5)
    with pytest.raises(ValueError, match="absorbed first and the wander nuisance last"):
        design.build(m, t, chans, ref, cands, catalogue=(design.BASELINE, softiron.TERM, wander.TERM, harmonics.TERM))
    with pytest.raises(ValueError, match="soft_iron"):
        design.build(m, t, chans, ref, cands, catalogue=(design.BASELINE, softiron.TERM, softiron.TERM))
