"""The tracker: the calibration in force follows the sensor, with bounded memory."""

import json
from dataclasses import replace

import numpy as np
import pytest

from magcal.fit import fit_calibration
from magcal.fit.tracker import Estimate, Tracker, TrackerConfig, Withdrawal
from magcal.fit.tracker_memory import WanderRate
from magcal.sim.physics import Motion, Physics, Scenario, demo_scenario

DRIFT = np.array([0.01, -0.006, 0.004])  # µT/s


def _run(scenario, n, rate=50.0):
    run = scenario.simulate(n, rate)
    return run, run.series.field_ut, run.series.t_s


def test_converges_to_the_truth_of_a_steady_sensor():
    run, m, t = _run(demo_scenario(3), 6000)
    trk = Tracker()
    events = trk.add_many(m, t)
    est = trk.estimate
    assert events and all(isinstance(e, Estimate) for e in events)
    assert est.model == "ellipsoid"
    assert np.abs(est.calibration.offset_ut - run.truth.offset_ut).max() < 0.15
    assert np.abs(est.calibration.soft_iron - run.truth.soft_iron).max() < 0.01
    assert est.wander_ut2_per_s == 0.0  # a steady sensor shows no wander
    # each change holds for the samples after it: indices are 0-based rows, increasing
    assert [e.sample for e in events] == sorted({e.sample for e in events})
    assert events[-1].sample <= len(m) - 1


@pytest.mark.slow
def test_follows_a_drifting_offset_that_a_static_fit_averages_away():
    sc = demo_scenario(5).with_physics(drift_ut_per_s=tuple(DRIFT))
    run, m, t = _run(sc, 30000)
    trk = Tracker()
    trk.add_many(m, t)
    now = run.truth.offset_ut + DRIFT * t[-1]
    tracked = np.linalg.norm(trk.estimate.calibration.offset_ut - now)
    static = np.linalg.norm(fit_calibration(m).calibration.offset_ut - now)
    assert trk.estimate.wander_ut2_per_s > 0
    assert tracked < 0.4 * static


@pytest.mark.slow
def test_a_sudden_change_is_followed_not_taken_for_outliers():
    sc = demo_scenario(4)
    a = sc.simulate(12000, 50.0).series
    b = sc.with_physics(hard_iron_ut=(30.5, -38.2, 14.8)).simulate(6000, 50.0, t0_s=240.0).series
    trk = Tracker()
    trk.add_many(a.field_ut, a.t_s)
    assert trk.changes == 0  # a steady sensor shows none
    trk.add_many(b.field_ut[:3000], b.t_s[:3000])
    assert trk.changes == 1
    assert np.abs(trk.estimate.calibration.offset_ut - [30.5, -38.2, 14.8]).max() < 0.5


def test_memory_is_bounded_whatever_the_length():
    cfg = TrackerConfig(bands=4, sectors=8, per_cell=4)
    _, m, t = _run(demo_scenario(2), 8000)
    trk = Tracker(cfg)
    trk.add_many(m, t)
    assert trk.memory.valid.sum() <= cfg.capacity == 128
    assert trk.n == 8000


def test_flat_turns_give_no_calibration():
    sc = replace(demo_scenario(5), motion=Motion("yaw"))
    _, m, t = _run(sc, 3000)
    trk = Tracker()
    events = trk.add_many(m, t)
    assert trk.estimate is None
    if events:  # a first solution on few samples may look pinned; it is then withdrawn
        assert isinstance(events[-1], Withdrawal)
        assert events[-1].to_dict()["offset_ut"] is None


def test_bad_samples_are_counted_and_do_not_disturb():
    run, m, t = _run(demo_scenario(4), 4000)
    bad = m.copy()
    bad[::97] = np.nan
    a, b = Tracker(), Tracker()
    a.add_many(m, t)
    b.add_many(bad, t)
    assert b.skipped == len(m[::97]) and b.n == len(m)
    assert np.abs(b.estimate.calibration.offset_ut - run.truth.offset_ut).max() < 0.2
    with pytest.raises(ValueError, match="samples but"):
        b.add_many(m[:10], t[:9])


def test_state_round_trip_continues_exactly():
    _, m, t = _run(demo_scenario(6), 5000)
    a = Tracker()
    a.add_many(m[:2500], t[:2500])
    state = json.loads(json.dumps(a.to_state()))
    b = Tracker.from_state(state)
    ea, eb = a.add_many(m[2500:], t[2500:]), b.add_many(m[2500:], t[2500:])
    assert [e.to_dict() for e in ea] == [e.to_dict() for e in eb]
    with pytest.raises(ValueError, match="not a tracker state"):
        Tracker.from_state({"kind": "something else"})
    old = {"grow_every": "ladder_every", "last_growth": "last_ladder", "cells_at_growth": "cells_at_ladder"}
    saved = {old.get(k, k): v for k, v in state.items()}  # as a tracker saved it before its model growth had its name
    saved["config"] = {old.get(k, k): v for k, v in state["config"].items()}
    assert "ladder_every" in saved["config"] and "last_ladder" in saved
    c = Tracker.from_state(saved)
    assert [e.to_dict() for e in c.add_many(m[2500:], t[2500:])] == [e.to_dict() for e in ea]


def test_wander_likelihood_finds_a_random_walk_and_not_a_per_visit_error():
    rng = np.random.default_rng(1)
    n = 4000
    dt = rng.uniform(0, 100, n)
    delta = rng.uniform(0, 0.1, n)
    other = rng.random(n) < 0.5
    s2 = 0.04
    walk = WanderRate()
    walk.add(rng.normal(0, np.sqrt(s2 * 2 + 0.002 * dt)), delta, other, dt)
    _, q = walk.solve()
    assert 0.001 < q < 0.004
    visits = WanderRate()  # an error shared within a visit, not growing with time
    visits.add(rng.normal(0, np.sqrt(s2 * (2 + 3 * other))), delta, other, dt)
    assert visits.solve()[1] == 0.0


def test_a_faster_stream_is_refitted_no_more_often_in_time():
    # 200 Hz: changes of the calibration in force come at most every refit_min_s, not every
    # refit_every samples; at 50 Hz (20 samples = 0.4 s) every refit_every samples as before
    for rate, gap_s in ((200.0, 0.4), (50.0, 0.4)):
        _, m, t = _run(demo_scenario(3), int(30 * rate), rate)
        events = Tracker().add_many(m, t)
        gaps = np.diff([e.t_s for e in events])
        assert len(events) > 20 and gaps.min() >= gap_s - 1e-6
        if rate == 50.0:
            assert np.all(np.diff([e.sample for e in events]) % 20 == 0)


@pytest.mark.parametrize("seed", [3, 7, 30])
def test_a_board_that_has_hardly_turned_puts_no_noise_sized_sphere_in_force(seed):
    # ±30° tilts from a standing start: the first 80–100 samples are a cloud a few µT across.
    # A sphere of 2–8 µT wraps it with every direction covered, so its condition passes; with
    # it in force the offset was 50 µT off (one field radius), and the memory was filed about
    # that centre. The Earth gives no field below 15 µT.
    truth = np.array([23.5, -41.2, 12.8])
    sc = Scenario(physics=Physics(hard_iron_ut=tuple(truth), distortion=tuple(map(tuple, np.diag([1.04, 0.97, 0.99]))),
                                  noise_ut=0.4), motion=Motion("tilt"), seed=seed)
    _, m, t = _run(sc, 3000)
    events = [e for e in Tracker().add_many(m, t) if isinstance(e, Estimate)]
    assert events
    assert min(e.calibration.field_ut for e in events) >= 15.0
    assert max(np.linalg.norm(e.calibration.offset_ut - truth) for e in events) < 10.0


def _soft_iron_board(motion, seed, truth):
    sc = Scenario(physics=Physics(hard_iron_ut=tuple(truth), distortion=tuple(map(tuple, np.diag([1.04, 0.97, 0.99]))),
                                  noise_ut=0.4), motion=Motion(motion), seed=seed)
    return _run(sc, 3000)


@pytest.mark.slow
def test_flat_turns_where_the_field_dips_put_no_wrong_centre_in_force():
    # The samples circle the field's cone. Every sphere through that circle fits them; the one
    # found first has the circle as its equator (field ≈ 25 µT, centre ≈ 40 µT off along z), and
    # at that sphere the information matrix looks well conditioned. Before the centre had to be
    # pinned, all ten seeds put such spheres in force; one (seed 6) still does.
    truth = np.array([23.5, -41.2, 12.8])
    started = 0
    for seed in range(1, 11):
        _, m, t = _soft_iron_board("yaw", seed, truth)
        started += any(isinstance(e, Estimate) for e in Tracker().add_many(m, t))
    assert started <= 1


@pytest.mark.parametrize("seed", [19, 20, 39])
def test_a_tumble_starts_from_a_centre_its_samples_pin(seed):
    # The first few hundred samples of these tumbles cover a patch that several spheres fit;
    # the first one taken was 30–55 µT off (field 16–37 µT), above the Earth-field floor.
    truth = np.array([23.5, -41.2, 12.8])
    _, m, t = _soft_iron_board("sphere", seed, truth)
    events = [e for e in Tracker().add_many(m, t) if isinstance(e, Estimate)]
    assert events
    assert max(np.linalg.norm(e.calibration.offset_ut - truth) for e in events) < 10.0


def test_a_recording_in_gauss_never_starts_and_says_which_field_it_saw():
    _, m, t = _run(demo_scenario(1), 3000)
    trk = Tracker()
    assert trk.add_many(m / 100.0, t) == []
    assert trk.estimate is None and 0.4 < trk.low_field_ut < 0.6
    back = Tracker.from_state(json.loads(json.dumps(trk.to_state())))
    assert back.low_field_ut == trk.low_field_ut
    assert Tracker(TrackerConfig(min_field_ut=0.0)).add_many(m / 100.0, t)  # the floor can be lifted


def test_config_refuses_nonsense():
    with pytest.raises(ValueError, match="min_field_ut"):
        TrackerConfig(min_field_ut=-1.0)
    with pytest.raises(ValueError, match="refit_min_s"):
        TrackerConfig(refit_min_s=float("nan"))
    with pytest.raises(ValueError, match="per_cell"):
        TrackerConfig(per_cell=0)
