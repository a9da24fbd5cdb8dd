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
