"""The offset wander placed in time: where a few stretches carry most of it, the limit says
where (its JSON ``where`` and its summary alike); a wander spread through the recording is
placed nowhere in particular."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.core.series import Series
from magcal.diagnose import diagnose

from test_diagnose import _sim, _wandering


def _wander_where(d):
    found = [x for x in d.to_dict()["limits"] if x["effect"] == "offset_wander"]
    assert found, f"no offset_wander limit; limits: {[x['effect'] for x in d.to_dict()['limits']]}"
    return found[0].get("where"), found[0]["summary"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [141, 142])
def test_an_offset_that_departs_for_a_few_seconds_is_placed_in_time_not_only_called_wander(seed):
    # a disturbance that comes and goes (a tool carried past the board): no step, no line, but
    # the wander it leaves sits in one stretch, and the limit says where
    run = _sim(seed)
    t = run.series.t_s
    bump = np.exp(-0.5 * ((t - 70.0) / 1.2) ** 2)
    d = diagnose(Series(t_s=t, field_ut=run.series.field_ut + np.outer(bump, [3.0, -2.0, 2.0])))
    where, summary = _wander_where(d)
    assert where is not None, summary
    assert any(a - 1.0 <= 70.0 <= b + 1.0 for a, b in where["time_s"]), where
    assert sum(b - a for a, b in where["time_s"]) <= 0.25 * np.ptp(t), where
    a, b = where["time_s"][0]
    assert f"{a:.1f}–{b:.1f} s" in summary


@pytest.mark.slow
def test_a_wander_spread_through_the_recording_is_placed_nowhere_in_particular():
    d = diagnose(_wandering(_sim(133), 133, amp_ut=0.8))
    where, summary = _wander_where(d)
    assert where is None, summary
    assert "most of it at" not in summary


def _jumps(d):
    return [x for x in d.to_dict()["limits"] if x["effect"] == "unexplained_structure" and "jump_ut" in x]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [141, 143])
def test_a_small_offset_step_the_step_search_does_not_prove_is_still_placed_in_time(seed):
    # 0.6 µT put down at 40 % of the span: under the local step search's threshold, but the
    # offset's wander is almost all that one change, and the remainder says when
    run = _sim(seed)
    t = run.series.t_s
    at_s = float(t[0] + 0.4 * np.ptp(t))
    d = diagnose(Series(t_s=t, field_ut=run.series.field_ut + np.outer(t >= at_s, [0.45, -0.3, 0.3])))
    assert "hard_iron_step" not in d.effects
    jumps = _jumps(d)
    assert len(jumps) == 1, [x["effect"] for x in d.to_dict()["limits"]]
    where, details = jumps[0]["where"], jumps[0]
    assert abs(where["time_s"][0] - at_s) <= 0.05 * np.ptp(t), where
    lo, hi = details["time_interval_s"]
    assert lo <= at_s <= hi
    assert 0.4 <= details["size_ut"] <= 0.8, details  # the step put in is 0.62 µT
    assert f"at {where['time_s'][0]:.1f} s" in jumps[0]["summary"]
    _, wander_summary = _wander_where(d)  # the wander's own statement tells the same story
    assert f"one jump at about {where['time_s'][0]:.1f} s" in wander_summary


@pytest.mark.slow
@pytest.mark.parametrize("seed", [133, 134])
def test_a_slow_wander_is_no_jump(seed):
    d = diagnose(_wandering(_sim(seed), seed, amp_ut=0.8))
    assert any(x["effect"] == "offset_wander" for x in d.to_dict()["limits"])
    assert _jumps(d) == []
