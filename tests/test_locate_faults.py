"""The data-fault screen: stuck axes, clipped rails, swapped axes and bad timestamps found with
their place on simulated and real recordings, and nothing claimed on clean ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.diagnose.locate import Kind
from magcal.diagnose.locate.faults import EFFECTS, FAULT_NAMES, screen
from magcal.fit import SphereAccumulator, fit_calibration
from magcal.sim.physics import Motion, Physics, Scenario

DATA = Path(__file__).parent / "data"
HARD = (21.0, -33.0, 8.0)


def _sim(seed=5, n=1000):
    run = Scenario(physics=Physics(hard_iron_ut=HARD, noise_ut=0.3), motion=Motion("sphere", period_s=20.0),
                   seed=seed).simulate(n, 50.0)
    return run.series.t_s.copy(), run.series.field_ut.copy()


def _real(name, mag=None):
    s = load_series(DATA / name, mag=mag) if mag is not None else load_series(DATA / name)
    return s.t_s.copy(), s.field_ut.copy()


def _only(found, effect):
    hits = [x for x in found if x.effect == effect]
    assert len(hits) == 1 and len(found) == 1, [x.summary for x in found]
    assert hits[0].kind is Kind.FAULT
    return hits[0]


def _stretch(t, a, b):
    return np.flatnonzero((t >= a) & (t <= b))


def test_a_clean_simulation_keeps_every_sample_and_claims_nothing():
    t, m = _sim()
    s = screen(t, m)
    assert s.found == () and s.keep.all()


@pytest.mark.parametrize("name,mag", [("hmc5883l_sunsided_full_sphere_every3rd.csv", None),
                                      ("ardupilot_log171_excerpt.bin", 1)])
def test_real_recordings_with_their_quantisation_and_repeated_reads_are_not_faults(name, mag):
    # the LSM303D of the ArduPilot log repeats whole readings up to 20 times (the first 800 hold
    # such runs): not a stuck axis
    t, m = _real(name, mag)
    assert screen(t[:800], m[:800]).found == ()


def test_a_stuck_axis_on_a_moving_board_is_found_where_it_is():
    t, m = _sim()
    rows = _stretch(t, 12.0, 16.0)
    m[rows, 1] = m[rows[0], 1]
    x = _only(screen(t, m).found, "stuck_axis")
    assert x.where["axis"] == "y"
    (a, b), = x.where["time_s"]
    assert abs(a - 12.0) < 0.1 and abs(b - 16.0) < 0.1
    assert set(rows[1:]) <= set(x.rows)


def test_a_stuck_axis_on_a_real_recording_is_found():
    t, m = _real("lsm9ds1_ckexplorer_every4th.csv")
    rows = np.arange(1200, 1240)  # 40 readings: about 3 s of the original 50 Hz recording
    m[rows, 2] = m[rows[0], 2]
    x = _only(screen(t, m).found, "stuck_axis")
    assert x.where["axis"] == "z" and abs(x.where["time_s"][0][0] - t[1200]) <= 1.0


def test_a_clipped_rail_is_found_on_its_axis_and_set_aside():
    t, m = _sim(seed=6)
    rail = np.quantile(m[:, 0], 0.95)
    m[:, 0] = np.minimum(m[:, 0], rail)
    s = screen(t, m)
    x = _only(s.found, "saturation")
    assert x.where["axis"] == "x" and x.params["rail_ut"] == pytest.approx(rail)
    assert 0.04 < x.params["share"] < 0.09  # quantised: readings already at the rail level count too
    assert not s.keep[m[:, 0] == rail].any()


def test_a_swapped_stretch_is_found_with_its_reading_and_the_fit_of_the_rest_recovers():
    t, m = _sim(seed=7)
    rows = _stretch(t, 10.0, 14.0)
    m[rows] = m[rows][:, [1, 0, 2]]
    s = screen(t, m)
    x = _only(s.found, "axis_swap")
    assert x.params["reading"] == "x↔y" and sorted(x.where["axis"]) == ["x", "y"]
    (a, b), = x.where["time_s"]
    assert abs(a - 10.0) < 1.0 and abs(b - 14.0) < 1.0
    fit = fit_calibration(m[s.keep], model="sphere")
    assert np.allclose(fit.calibration.offset_ut, HARD, atol=1.0)


def test_a_flipped_axis_on_a_real_recording_is_found():
    t, m = _real("lsm9ds1_ckexplorer_every4th.csv")
    m[1500:1800, 1] *= -1.0
    x = _only(screen(t, m).found, "axis_swap")
    assert x.params["reading"] == "−y"
    (a, b), = x.where["time_s"]
    assert abs(a - t[1500]) <= 0.05 * (t[-1] - t[0]) and abs(b - t[1799]) <= 0.05 * (t[-1] - t[0])


def test_repeated_and_backward_timestamps_are_counted_where_they_are():
    t, m = _sim(n=600)
    t[[100, 300]] = t[[99, 299]]
    t[450], t[451] = t[451], t[450]
    s = screen(t, m)
    rep = [x for x in s.found if x.effect == "repeated_timestamps"][0]
    back = [x for x in s.found if x.effect == "out_of_order_timestamps"][0]
    assert rep.params["n_samples"] == 2 and list(rep.rows) == [100, 300]
    assert back.params["n_samples"] == 1 and list(back.rows) == [451]
    assert s.n_set_aside == 3


def test_flagged_samples_are_left_out_and_bad_input_is_named():
    t, m = _sim(n=600)
    valid = np.ones(len(t), bool)
    valid[:10] = False
    assert screen(t, m, valid).n_set_aside == 10
    with pytest.raises(ValueError, match="m_ut must be"):
        screen(t, m[:, :2])
    with pytest.raises(ValueError, match="valid has"):
        screen(t, m, valid[:5])


def test_the_table_rows_are_faults_named_by_the_screen():
    assert tuple(e.name for e in EFFECTS) == FAULT_NAMES
    assert all(e.kind is Kind.FAULT for e in EFFECTS)


def test_moving_data_with_a_swapped_stretch_is_not_called_a_still_cloud():
    # a board turned over the whole sphere, a tenth of it read with x and y swapped: the sphere's
    # residual is large against the spread, but the board moved
    run = Scenario(physics=Physics(hard_iron_ut=(150.0, -200.0, 20.0), noise_ut=0.3),
                   motion=Motion("sphere", period_s=20.0), seed=3).simulate(1500, 50.0)
    m = run.series.field_ut.copy()
    m[600:750] = m[600:750][:, [1, 0, 2]]
    acc = SphereAccumulator()
    acc.add_batch(m)
    out = acc.solve()
    assert out or "held still" not in out.message


def _low_rate(seed, n, rate_hz, hard=HARD):
    run = Scenario(physics=Physics(hard_iron_ut=hard, noise_ut=0.3), motion=Motion("sphere", period_s=60.0),
                   seed=seed).simulate(n, rate_hz)
    return run.series.t_s.copy(), run.series.field_ut.copy()


def test_five_swapped_readings_of_a_slow_log_are_found_by_their_total_evidence_and_its_control_is_clean():
    # 1 Hz: a 5 s swap is five readings, each far off the surface as read and on it swapped
    t, m = _low_rate(seed=8, n=300, rate_hz=1.0)
    assert screen(t, m).found == ()
    m[150:155] = m[150:155][:, [1, 0, 2]]
    x = _only(screen(t, m).found, "axis_swap")
    assert x.params["reading"] == "x↔y" and x.where["time_s"] == [[t[150], t[154]]]
    assert x.evidence["evidence_nats"] > x.evidence["threshold_nats"]


def test_four_readings_of_a_slow_log_stuck_at_a_rail_are_a_stuck_axis_not_wander():
    # 1 Hz and a board turning fast: y reads its rail for four readings (4 s) while x and z move;
    # the diagnosis names a stuck axis where it is (with five readings the least, it said the
    # offset wandered at 150–164 s and fitted the rail into the calibration)
    from magcal.core.series import Series
    from magcal.diagnose import diagnose

    t, m = _low_rate(seed=8, n=300, rate_hz=1.0)
    m[150:154, 1] = -1.5 * np.max(np.abs(m))
    d = diagnose(Series(t_s=t, field_ut=m)).to_dict()
    stuck = [x for x in d["findings"] if x["effect"] == "stuck_axis"]
    assert len(stuck) == 1, [x["effect"] for x in d["findings"]]
    assert stuck[0]["where"]["axis"] == "y" and stuck[0]["where"]["time_s"] == [[t[150], t[153]]]
    assert "offset_wander" not in [x["effect"] for x in d["limits"]]


@pytest.mark.parametrize("held", [3, 4])
def test_a_stuck_run_is_counted_in_readings_when_the_logger_writes_each_reading_twice(held):
    # the same 1 Hz take logged at 2 Hz, every reading written twice (a logger faster than its
    # sensor): y at its rail for three readings is six rows but three readings, under the least a
    # stuck run needs; for four readings it is a stuck axis
    t, m = _low_rate(seed=8, n=300, rate_hz=1.0)
    t2, m2 = np.repeat(t, 2) + np.tile([0.0, 0.5], len(t)), np.repeat(m, 2, axis=0)
    m2[300 : 300 + 2 * held, 1] = -1.5 * np.max(np.abs(m))
    stuck = [x for x in screen(t2, m2).found if x.effect == "stuck_axis"]
    if held == 3:
        assert stuck == []
    else:
        assert len(stuck) == 1 and stuck[0].where == {"time_s": [[t[150], t[153] + 0.5]], "axis": "y"}


def test_a_swap_the_radius_cannot_see_is_found_by_the_jumps_at_its_two_ends():
    # x and y offsets equal: swapping x and y maps the sphere onto itself, so only the trajectory
    # tells, jumping into the stretch and out of it and continuous read back swapped
    t, m = _low_rate(seed=9, n=1500, rate_hz=25.0, hard=(20.0, 20.0, -5.0))
    assert screen(t, m).found == ()
    rows = _stretch(t, 30.0, 34.0)
    m[rows] = m[rows][:, [1, 0, 2]]
    x = _only(screen(t, m).found, "axis_swap")
    assert x.params["reading"] == "x↔y" and x.evidence["view"] == "edges"
    (a, b), = x.where["time_s"]
    assert abs(a - 30.0) < 0.1 and abs(b - 34.0) < 0.1


@pytest.mark.slow
def test_a_strong_line_on_one_axis_is_a_line_not_an_axis_swap():
    # a 3.8 µT line on x at a sixth of the sample rate steps x by several µT every reading while
    # y and z step little: scored against one 3-D typical step, its ordinary steps looked like
    # the jumps at the ends of a negated stretch (axis_swap at 9–42 s of this real excerpt)
    from magcal.core.series import Series
    from magcal.diagnose import diagnose

    s = load_series(DATA / "hmc5883l_sunsided_full_sphere_every3rd.csv")
    rate_hz = 1.0 / float(np.median(np.diff(s.t_s)))
    m = s.field_ut.copy()
    m[:, 0] += 3.8 * np.cos(2 * np.pi * rate_hz / 6.0 * s.t_s)
    d = diagnose(Series(t_s=s.t_s, field_ut=m)).to_dict()
    effects = [x["effect"] for x in d["findings"]]
    assert "axis_swap" not in effects, effects
    lines = [x for x in d["findings"] if x["effect"] == "narrowband_line"]
    assert any(abs(x["where"]["frequency_hz"] - rate_hz / 6.0) < 0.02 * rate_hz / 6.0 for x in lines), effects
