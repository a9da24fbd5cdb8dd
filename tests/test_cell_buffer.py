"""The one sample buffer: what a full cell gives up under each policy, re-filing about a new
centre, and the session's earlier saved state still loading."""

import json

import numpy as np
import pytest

from magcal.core.sample import Sample
from magcal.fit.accumulator import SphereAccumulator
from magcal.fit.cell_buffer import CellBuffer, WhenFull
from magcal.logic.session import Session

# A session's kept samples as the earlier buffer saved them (its ``to_state``): samples in
# arrival order, each with an aux dict; re-binned about this centre the last cell (band 1,
# sector 1) holds three samples for its two places.
EARLIER_KEPT = {
    "per_cell": 2, "bands": 2, "sectors": 2, "centre_ut": [10.0, -20.0, 0.0],
    "field_ut": [[60.0, 0.0, 5.0], [62.0, 1.0, 4.0], [61.0, -1.0, 6.0], [-40.0, 0.0, -3.0], [10.0, 0.0, -49.0]],
    "aux": [{"t_s": 0.0, "temp_c": 25.0}, {"t_s": 0.5, "temp_c": 25.0}, {"t_s": 1.0, "temp_c": 25.0},
            {"t_s": 1.5, "temp_c": 25.0}, {"t_s": 2.5, "temp_c": 25.0}],
}


def _one_cell(when_full: WhenFull, times) -> CellBuffer:
    buf = CellBuffer(1, 1, 3, when_full=when_full, centre_ut=np.zeros(3))
    for k, t in enumerate(times):
        buf.add(50.0, float(k), 0.0, t)
    return buf


def test_a_full_cell_refuses_the_newcomer_under_first_come():
    buf = _one_cell(WhenFull.REFUSE, [0.0, 1.0, 10.0])
    assert not buf.add(50.0, 9.0, 0.0, 20.0)
    assert sorted(buf.samples()[2]) == [0.0, 1.0, 10.0]


def test_a_full_cell_gives_up_the_older_of_its_two_closest_samples_when_thinning():
    buf = _one_cell(WhenFull.THIN, [0.0, 1.0, 10.0])
    assert buf.add(50.0, 9.0, 0.0, 20.0)
    assert sorted(buf.samples()[2]) == [1.0, 10.0, 20.0]  # 0 and 1 were closest: 0 went


def _crowded(policy: WhenFull) -> CellBuffer:
    """Four directions in four cells about the origin, re-filed about a centre that puts them
    all in one cell (band 1, sector 1) with two places."""
    buf = CellBuffer(2, 2, 2, when_full=policy, centre_ut=np.zeros(3))
    for t, p in enumerate([(50.0, 5.0, 40.0), (50.0, -5.0, 40.0), (50.0, 5.0, -40.0), (50.0, -5.0, -40.0)]):
        buf.add(*p, float(t))
    assert buf.coverage() == 1.0
    assert not buf.rebin([0.0, -100.0, -100.0])  # refused unforced: it would crowd four cells into one
    assert buf.rebin([0.0, -100.0, -100.0], force=True)
    return buf


def test_re_filing_thins_a_crowded_cell_to_its_newest():
    buf = _crowded(WhenFull.THIN)
    assert len(buf) == 2 and sorted(buf.samples()[2]) == [2.0, 3.0]


def test_re_filing_a_first_come_buffer_gives_up_nothing_it_kept():
    buf = _crowded(WhenFull.REFUSE)
    assert len(buf) == 4 and buf.cell_counts().tolist() == [0, 0, 0, 4]
    assert not buf.add(0.0, 0.0, 0.0, 4.0)  # into the crowded cell: refused
    for t in range(5, 9):  # cell 0 (band 0, sector 0) has places for two, the buffer for four
        buf.add(-50.0, -150.0, -150.0, float(t))
    assert buf.cell_counts().tolist() == [2, 0, 0, 4] and len(buf) == 6
    assert sorted(buf.samples()[2]) == [0.0, 1.0, 2.0, 3.0, 5.0, 6.0]
    back = CellBuffer.from_state(json.loads(json.dumps(buf.to_state())))
    assert np.array_equal(back.field_ut, buf.field_ut) and back.cell_counts().tolist() == [2, 0, 0, 4]
    assert back.add(-50.0, -50.0, -150.0, 9.0) and back.add(-50.0, -50.0, -150.0, 10.0)  # cell 1
    assert len(back) == back.capacity == 8
    assert not back.add(-50.0, -150.0, -50.0, 11.0)  # cell 2 is empty, but every slot is used
    assert back.field_ut[-2:].tolist() == [[-50.0, -50.0, -150.0]] * 2


def test_the_sessions_earlier_saved_samples_still_load():
    buf = CellBuffer.from_state(json.loads(json.dumps(EARLIER_KEPT)))
    assert buf.when_full is WhenFull.REFUSE and (buf.bands, buf.sectors, buf.per_cell) == (2, 2, 2)
    assert np.array_equal(buf.centre_ut, [10.0, -20.0, 0.0])
    # every sample kept, in the order it came, counted as that buffer counted it
    assert buf.field_ut.tolist() == EARLIER_KEPT["field_ut"]
    assert buf.cell_counts().tolist() == [0, 2, 0, 3] and buf.coverage() == 0.5
    assert sorted(buf.samples()[2]) == [0.0, 0.5, 1.0, 1.5, 2.5]
    assert not buf.add(60.0, 0.0, 5.0, 3.0)  # its crowded cell takes no more
    back = CellBuffer.from_state(json.loads(json.dumps(buf.to_state())))
    assert np.array_equal(back.field_ut, buf.field_ut) and back.when_full is WhenFull.REFUSE


def test_a_session_saved_with_the_earlier_buffer_resumes():
    acc = SphereAccumulator()
    for m in EARLIER_KEPT["field_ut"]:
        acc.add(np.asarray(m, dtype=np.float64))
    state = {"model": "auto", "counters": {"samples_in": 6}, "accumulator": acc.to_state(), "kept": EARLIER_KEPT}
    s = Session.from_state(json.loads(json.dumps(state)))
    assert len(s.kept) == 5 and s.progress()["kept"] == 5
    s.add(Sample(seq=7, t_s=3.0, field_ut=(10.0, -40.0, -30.0)))  # into the empty cell 0
    assert len(s.kept) == 6 and s.kept.cell_counts().tolist() == [1, 2, 0, 3]


def test_bad_buffers_and_states_are_refused_by_name():
    with pytest.raises(ValueError, match="per_cell"):
        CellBuffer(per_cell=0)
    with pytest.raises(ValueError, match="when_full"):
        CellBuffer(when_full="refuse")
    with pytest.raises(ValueError, match="capacity"):
        CellBuffer.from_state({**EARLIER_KEPT, "field_ut": [[50.0, 0.0, 0.0]] * 9, "aux": [{}] * 9})
    with pytest.raises(ValueError, match="malformed"):
        CellBuffer.from_state({k: v for k, v in CellBuffer().to_state().items() if k != "when_full"})
    with pytest.raises(ValueError, match="per_cell"):
        CellBuffer(per_cell=4).load_state(CellBuffer(per_cell=8).to_state())
