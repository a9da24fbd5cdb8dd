"""The live view's state (magcal.logic.view): what the page shows, computed without a browser."""

import json

import numpy as np

from magcal.core.calibration import Calibration
from magcal.core.sample import Sample
from magcal.fit.coverage import cell_centres
from magcal.logic.gates import Gates
from magcal.logic.session import Session
from magcal.logic.view import WriteState, motioncal_numbers, next_turn, page_state
from magcal.sim.physics import Motion, Scenario, demo_scenario


def _samples(scenario, n, rate=50.0):
    run = scenario.simulate(n, rate)
    s = run.series
    return [Sample(seq=i, t_s=float(s.t_s[i]), field_ut=tuple(s.field_ut[i]), raw=tuple(int(v) for v in run.raw[i]),
                   st2=int(run.st2[i])) for i in range(n)]


def _sphere(n, offset, radius, seed=1):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return offset + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_gaps_shrink_and_the_numbers_appear_as_a_session_fills():
    s = Session(Gates())
    items = _samples(demo_scenario(5), 1500)
    s.add_many(items[:150])
    early = page_state(s, elapsed_s=1.5, timeout_s=60)
    s.add_many(items[150:])
    late = page_state(s, elapsed_s=15.0, timeout_s=60)
    assert early.write is WriteState.PENDING and early.turn is not None
    assert late.motioncal.gaps_pct < early.motioncal.gaps_pct
    assert len(late.points) > len(early.points) and late.kept == len(late.points)
    assert late.live["offset_ut"] is not None and late.motioncal.fit_error_pct is not None
    assert late.rate_hz == round(1500 / 15.0, 1) and late.time_left_s == 45.0
    json.dumps(late.to_dict())  # the page receives it as JSON


def test_a_well_calibrated_full_sphere_scores_near_zero_and_a_shifted_one_wobbles():
    m = _sphere(3000, np.array([10.0, -5.0, 3.0]), 50.0)
    good = Calibration(offset_ut=[10.0, -5.0, 3.0], field_ut=50.0)
    counts = np.ones(128)
    n = motioncal_numbers(m, good, counts, 8, 16)
    assert n.gaps_pct == 0.0 and n.variance_pct < 0.5 and n.fit_error_pct < 0.5 and n.wobble_pct < 0.5
    half = motioncal_numbers(m[m[:, 2] > 3.0], good, counts, 8, 16)
    assert half.wobble_pct < 0.5  # a half-covered sphere, well centred, does not wobble
    off = Calibration(offset_ut=[0.0, -5.0, 3.0], field_ut=50.0)  # 10 µT of offset missed on x
    bad = motioncal_numbers(m, off, counts, 8, 16)
    assert 15.0 < bad.wobble_pct < 25.0 and bad.variance_pct > 5.0 and bad.fit_error_pct > 5.0


def test_before_any_calibration_only_the_gaps_are_known():
    counts = np.zeros(128)
    counts[:32] = 3
    n = motioncal_numbers(np.zeros((0, 3)), None, counts, 8, 16)
    assert n.gaps_pct == 75.0 and n.variance_pct is None and n.wobble_pct is None and n.fit_error_pct is None


def test_the_next_turn_names_the_side_of_the_nearest_empty_cell():
    centres = cell_centres(8, 16)
    counts = np.ones(128)
    top = int(np.argmax(centres[:, 2]))
    counts[top] = 0
    turn = next_turn(counts, 8, 16, here=[0.0, 0.0, 1.0])
    assert turn.side.startswith("+Z") and turn.angle_deg < 30 and turn.here == (0.0, 0.0, 1.0)
    assert next_turn(np.ones(128), 8, 16, here=[1, 0, 0]) is None  # nothing left to fill


def test_flat_turns_wait_on_coverage_and_point_at_an_empty_cell():
    from magcal.fit.coverage import cell_index

    s = Session(Gates())
    s.add_many(_samples(Scenario(motion=Motion("yaw"), seed=2), 1500))
    v = page_state(s, elapsed_s=30.0, timeout_s=60)
    assert "min_coverage" in v.waiting_on and v.motioncal.gaps_pct > 50
    if v.live["offset_ut"] is None:  # no calibration yet: the directions the cells count, on the sphere
        assert np.allclose(np.linalg.norm(v.points, axis=1), 1.0, atol=0.01)
    target = int(cell_index(np.array([v.turn.target]), v.bands, v.sectors)[0])
    assert v.cells[target] == 0 and v.turn.angle_deg is not None


def test_the_write_is_shown_verified_only_after_the_read_back():
    s = Session(Gates())
    for smp in _samples(demo_scenario(5), 4000):
        s.add(smp)
        if s.ready():
            break
    s.solve()
    assert page_state(s).write is WriteState.PENDING
    s.begin_write()
    assert page_state(s).write is WriteState.WRITING
    s.written()
    s.verified(True)
    done = page_state(s, written=True, verified=True)
    assert done.write is WriteState.VERIFIED and done.turn is None and done.waiting_on == []
    assert done.live["offset_sigma_ut"] is not None


def test_a_daemon_that_goes_on_collecting_shows_what_it_wrote_and_verified():
    s = Session(Gates())
    held = Calibration(offset_ut=[1.0, 2.0, 3.0], field_ut=48.0)
    v = page_state(s, held=held).to_dict()
    assert v["write"] == "pending" and v["held"] == {"offset_ut": [1.0, 2.0, 3.0], "field_ut": 48.0, "verified": True}
    assert page_state(s).held is None


def test_a_failed_or_unwritten_calibration_is_never_shown_verified():
    from magcal.logic import failures

    s = Session(Gates())
    s.fail(failures.TIMEOUT, "timed out after 60 s before every gate passed — failing: min_coverage")
    v = page_state(s, written=False, verified=False)
    assert v.write is WriteState.FAILED and "min_coverage" in v.message
    s = Session(Gates())
    for smp in _samples(demo_scenario(5), 4000):
        s.add(smp)
        if s.ready():
            break
    s.solve()
    s.finish_without_write()  # --no-write, or a read-only source
    assert page_state(s, written=False, verified=False).write is WriteState.NOT_WRITTEN
