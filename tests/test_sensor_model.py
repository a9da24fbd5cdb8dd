"""The sensor model as a value: serialised, drawn, and driving the simulated board."""

import dataclasses
import json

import numpy as np
import pytest
import yaml

from magcal.app.sensor_file import load_model, save_model
from magcal.core.calibration import Calibration
from magcal.core.errors import InputError
from magcal.sim import wander
from magcal.sim.disturbance import Disturbances
from magcal.sim.model import SCHEMA, SensorModel
from magcal.sim.physics import Motion, Physics, Scenario, demo_scenario
from magcal.sim.wander import WanderComponent


def _model(**kw):
    cal = Calibration(offset_ut=[20.0, -30.0, 5.0], field_ut=48.0,
                      soft_iron=[[1.05, 0.01, 0.0], [0.01, 0.97, 0.0], [0.0, 0.0, 0.98]],
                      coef_ut_per_unit={"current_a": [0.5, -0.2, 0.1]}, reference={"current_a": 0.0})
    base = dict(calibration=cal, noise_ut=(0.3, 0.3, 0.4), quantum_ut=(0.15, 0.15, 0.15),
                wander=(WanderComponent(0.3, 20.0), WanderComponent((0.1, 0.1, 0.2), 0.5)), glitch_rate=0.001,
                glitch_ut=(2.0, 3.0, 3.5, 6.0, 15.0),
                nonlinearity_ut=(0.2,) + (0.0,) * 15, temp_gain_per_c=1e-3, saturation_ut=800.0,
                disturbances=Disturbances(0.05, (2.0, 6.0), (0.2, 3.0), 0.7))
    base.update(kw)
    return SensorModel(**base)


@pytest.mark.parametrize("suffix", ["yaml", "json"])
def test_model_file_round_trip_keeps_every_value(tmp_path, suffix):
    m = _model()
    path = tmp_path / f"m.{suffix}"
    save_model(m, path)
    text = path.read_text()
    assert SCHEMA in text and "noise_ut" in text and "tau_s" in text
    back = load_model(path)
    assert back.to_dict() == m.to_dict()


def test_a_malformed_model_file_is_refused_with_the_problem_named(tmp_path):
    good = _model().to_dict()
    cases = {
        "schema": ({**good, "schema": "magcal.sensor-model/99"}, "schema"),
        "missing": ({k: v for k, v in good.items() if k != "offset_ut"}, "offset_ut"),
        "negative": ({**good, "noise_ut": [0.1, -1, 0.1]}, "noise_ut"),
        "tau": ({**good, "wander": [{"sigma_ut": [1, 1, 1], "tau_s": 0}]}, "tau_s"),
        "term": ({**good, "nonlinearity_ut": {"y9_x": 1.0}}, "y9_x"),
    }
    for name, (d, word) in cases.items():
        p = tmp_path / f"{name}.yaml"
        p.write_text(yaml.safe_dump(d))
        with pytest.raises(InputError, match=word):
            load_model(p)
    p = tmp_path / "junk.yaml"
    p.write_text("a: [unclosed")
    with pytest.raises(InputError, match="junk.yaml"):
        load_model(p)


def test_wander_is_a_function_of_seed_and_time_alone():
    comps = (WanderComponent(0.5, 3.0),)
    t = np.linspace(0, 60, 3001)
    a = wander.draw(comps, 7, t)[0]
    shuffled = np.random.default_rng(0).permutation(len(t))
    b = wander.draw(comps, 7, t[shuffled])[0]
    assert np.allclose(a[shuffled], b)
    assert not np.allclose(a, wander.draw(comps, 8, t)[0])


def test_wander_has_the_ou_variance_and_correlation_time():
    comps = (WanderComponent(0.5, 3.0),)
    t = np.array([0.0, 3.0])
    x = np.array([wander.draw(comps, s, t)[0] for s in range(600)])  # (seeds, 2, 3)
    var = x[:, 0, :].var()
    corr = np.mean(x[:, 0, :] * x[:, 1, :]) / var
    assert 0.25 * 0.85 < var < 0.25 * 1.15
    assert abs(corr - np.exp(-1.0)) < 0.08


def test_the_board_draws_from_the_one_model():
    sc = demo_scenario(3)
    sensor = sc.sensor
    assert sensor.calibration.close_to(sc.physics.truth())
    run = sc.simulate(500)
    # the same stream through an explicit model gives the same readings before the chip's counts
    m1, _ = sc.field_ut(run.series.t_s, np.arange(500))
    m2, _ = dataclasses.replace(sc, model=sensor).field_ut(run.series.t_s, np.arange(500))
    assert np.allclose(m1, m2)


def test_a_model_with_wander_makes_autocorrelated_residuals_on_the_board():
    sm = dataclasses.replace(demo_scenario(1).sensor, wander=(WanderComponent(0.6, 10.0),), noise_ut=(0.2,) * 3)
    sc = Scenario(physics=Physics(), motion=Motion("sphere", period_s=20.0), seed=5, model=sm)
    s = sc.simulate(3000).series
    e = np.linalg.norm(sm.calibration.correct(s.field_ut), axis=1) - sm.calibration.field_ut
    e = e - e.mean()
    assert (e[:-1] @ e[1:]) / (e @ e) > 0.6
    still = Scenario(physics=Physics(), seed=5, model=dataclasses.replace(sm, wander=())).simulate(3000).series
    e0 = np.linalg.norm(sm.calibration.correct(still.field_ut), axis=1) - sm.calibration.field_ut
    e0 = e0 - e0.mean()
    assert abs((e0[:-1] @ e0[1:]) / (e0 @ e0)) < 0.1


def test_quantum_and_saturation_show_in_the_readings():
    sm = _model(saturation_ut=60.0, wander=(), glitch_rate=0.0)
    u = np.random.default_rng(1).standard_normal((400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    m, valid = sm.simulate(u, np.arange(400) / 50.0, {"current_a": np.zeros(400)}, seed=2)
    assert np.allclose(m / 0.15, np.round(m / 0.15))
    assert (~valid).any() and valid.any()
    assert np.all(np.abs(m[~valid]).max(axis=1) >= 60.0 - 1e-9)


def test_removing_an_effect_leaves_the_rest():
    sm = _model()
    assert set(sm.effects()) >= {"soft_iron", "current_a", "wander", "nonlinearity", "glitches",
                                 "temperature_gain", "saturation"}
    for effect in sm.effects():
        less = sm.without(effect)
        assert effect not in less.effects()
        assert set(less.effects()) == set(sm.effects()) - {effect}
    with pytest.raises(ValueError, match="no effect"):
        sm.without("magic")


def test_model_dict_is_json_with_units_in_its_keys():
    d = _model().to_dict()
    json.dumps(d)
    assert d["schema"] == SCHEMA
    for key in ("offset_ut", "field_ut", "noise_ut", "quantum_ut", "temp_gain_per_c", "saturation_ut", "rate_hz"):
        assert key in d
    assert d["wander"][0].keys() == {"sigma_ut", "tau_s"}
    assert d["glitches"].keys() == {"rate_per_sample", "size_ut", "axis_share", "radial_share", "period_s", "jitter_s"}


def test_a_model_that_cannot_be_written_is_a_named_error(tmp_path):
    with pytest.raises(InputError, match="cannot write"):
        save_model(_model(), tmp_path / "no" / "such" / "m.yaml")


def test_disturbances_are_a_function_of_seed_and_time_and_hold_their_rate_size_and_sign():
    d = Disturbances(rate_per_s=0.1, size_ut=(2.0, 8.0), duration_s=(0.5, 2.0), up_share=0.75)
    t = np.arange(0, 4000, 0.1)
    x = d.draw(3, t)
    shuffled = np.random.default_rng(0).permutation(len(t))
    assert np.allclose(d.draw(3, t[shuffled]), x[shuffled])
    assert not np.allclose(d.draw(4, t), x)
    on = x != 0
    starts = np.count_nonzero(np.diff(on.astype(int)) == 1)
    assert 0.08 * 4000 < starts < 0.12 * 4000  # about rate × span (overlaps merge a few)
    assert 2.0 <= np.median(np.abs(x[on])) <= 8.0 and np.max(np.abs(x)) < 2 * 8.0  # overlaps add
    assert 0.65 < np.mean(x[on] > 0) < 0.85
    with pytest.raises(ValueError, match="up_share"):
        Disturbances(0.1, (1.0, 2.0), (0.5, 1.0), 1.5)


def test_disturbances_with_events_hold_one_pair_each_and_survive_the_file(tmp_path):
    """A process given the (size, duration) pairs a recording showed draws each event as one
    of them — a 5 µT hold lasts 0.2 s, a 2 µT one 3 s, never 5 µT for 3 s — and a version-6
    file, which has no pairs, is read as the log-uniform ranges it held."""
    d = Disturbances(rate_per_s=0.05, size_ut=(2.0, 6.0), duration_s=(0.2, 3.0), up_share=1.0,
                     events=((5.0, 0.2), (2.0, 3.0)))
    x = d.draw(5, np.arange(0.0, 20000.0, 0.01))

    def runs_at(level):  # lengths (samples) of the runs where x holds ``level``
        edges = np.diff(np.concatenate([[0], (x == level).astype(int), [0]]))
        return np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)

    assert len(runs_at(5.0)) > 300 and runs_at(5.0).max() <= 21  # (overlapping holds add: 2 + 5 = 7)
    assert len(runs_at(2.0)) > 300 and np.median(runs_at(2.0)) > 250
    m = _model(disturbances=d)
    save_model(m, tmp_path / "m.yaml")
    assert load_model(tmp_path / "m.yaml").disturbances == d
    old = m.to_dict()
    old["schema"] = "magcal.sensor-model/6"
    del old["disturbances"]["events"]
    assert SensorModel.from_dict(old).disturbances.events == ()
    with pytest.raises(ValueError, match="at most duration_s"):
        Disturbances(0.05, (2.0, 6.0), (0.2, 1.0), events=((2.0, 3.0),))


@pytest.mark.slow
def test_disturbances_learned_from_a_recording_that_has_them_and_not_from_one_without():
    from magcal.diagnose import twin

    cal = Calibration(offset_ut=[20.0, -30.0, 5.0], field_ut=48.0)
    truth = Disturbances(rate_per_s=0.05, size_ut=(3.0, 6.0), duration_s=(0.5, 1.5), up_share=0.5)
    sm = SensorModel(calibration=cal, noise_ut=(0.3, 0.3, 0.3), disturbances=truth)

    def learned(model):
        s = Scenario(physics=Physics(field_ut=48.0), motion=Motion("sphere", period_s=20.0), seed=8,
                     model=model).simulate(30000).series
        return twin.learn(s, cal)

    d = learned(sm).disturbances
    assert d is not None
    assert 0.5 < d.rate_per_s / truth.rate_per_s < 2.0
    assert 2.0 < d.size_ut[1] < 9.0
    assert learned(sm.without("disturbances")).disturbances is None


def test_a_first_version_model_file_is_still_read(tmp_path):
    d = _model(glitch_ut=(4.0, 15.0)).to_dict()
    d["schema"] = "magcal.sensor-model/1"
    assert SensorModel.from_dict(d).glitch_ut == (4.0, 15.0)


def test_a_third_version_model_file_has_its_glitches_at_random_reads():
    d = _model().to_dict()
    d["schema"] = "magcal.sensor-model/3"
    for key in ("period_s", "jitter_s"):
        del d["glitches"][key]
    back = SensorModel.from_dict(d)
    assert back.glitch_period_s is None and back.glitch_rate == 0.001
    with pytest.raises(ValueError, match="jitter_s needs a period_s"):
        _model(glitch_jitter_s=0.01)


def test_a_fourth_version_model_file_has_no_glitches_along_the_field():
    d = _model().to_dict()
    d["schema"] = "magcal.sensor-model/4"
    del d["glitches"]["radial_share"]
    assert SensorModel.from_dict(d).glitch_radial_share == 0.0
    with pytest.raises(ValueError, match="radial shares"):
        _model(glitch_axis_share=0.6, glitch_radial_share=0.6)


def test_a_glitch_along_the_field_reads_the_fields_magnitude_wrong_by_its_size_on_the_simulated_board():
    """The simulated board and the twin share the one model: a glitch along the field moves the
    corrected reading along the field direction by its size (2–8 µT), nothing across it."""
    sm = _model(glitch_rate=0.05, glitch_ut=(2.0, 8.0), glitch_radial_share=1.0, glitch_period_s=None,
                glitch_jitter_s=0.0, wander=(), disturbances=None)
    sc = Scenario(physics=Physics(), motion=Motion("sphere", period_s=20.0), seed=9, model=sm)
    k = np.arange(4000)
    t = k / 50.0
    _, glitch = sc.field_ut(t, k)
    hit = np.any(glitch != 0, axis=1)
    gh = glitch[hit] @ np.asarray(sm.calibration.soft_iron).T  # the glitch in the corrected frame
    u = sc.earth_body_ut(t[hit])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    along = np.sum(gh * u, axis=1)
    assert 0.04 < hit.mean() < 0.06
    assert np.allclose(np.linalg.norm(gh, axis=1), np.abs(along)) and np.all((np.abs(along) > 1.99) & (np.abs(along) < 8.01))


def test_a_pulse_train_glitches_its_reads_at_its_period_whichever_way_the_board_is_read():
    """Glitches from a source on its own clock: at 50 Hz, a pulse every 0.2 s (10 reads) with
    half of the pulses glitching gives 5 % of reads glitched, nearly always a whole number of
    10 reads apart; the simulated board read in any order gives the same glitches, and a higher rate
    keeps those a lower one made."""
    sm = _model(glitch_rate=0.05, glitch_period_s=0.2, glitch_jitter_s=0.004, wander=(), disturbances=None)
    sc = Scenario(physics=Physics(), motion=Motion("sphere", period_s=20.0), seed=9, model=sm)
    k = np.arange(20000)
    t = k / 50.0
    _, glitch = sc.field_ut(t, k)
    hit = np.flatnonzero(np.any(glitch != 0, axis=1))
    assert 0.045 < len(hit) / len(k) < 0.055
    assert np.mean(np.diff(hit) % 10 == 0) > 0.9
    order = np.random.default_rng(1).permutation(len(k))
    _, shuffled = sc.field_ut(t[order], k[order])
    assert np.array_equal(np.any(shuffled != 0, axis=1), np.any(glitch != 0, axis=1)[order])
    d = sm.draws(t, seed=4)
    more = dataclasses.replace(sm, glitch_rate=0.08).draws(t, seed=4)
    low, high = np.any(d.glitch_ut != 0, axis=1), np.any(more.glitch_ut != 0, axis=1)
    assert np.all(high[low]) and high.sum() > 1.4 * low.sum()
    assert np.mean(np.diff(np.flatnonzero(low)) % 10 == 0) > 0.9


def test_glitch_sizes_follow_their_quantiles_and_two_make_them_log_uniform():
    from magcal.sim.model import glitch_parts

    def sizes(q):
        g, _ = glitch_parts(np.random.default_rng(5), 200_000, 0.5, q)
        return np.linalg.norm(g[np.any(g != 0, axis=1)], axis=1)

    s = sizes((1.0, 1.5, 2.0, 2.2, 8.0))
    assert np.allclose(np.quantile(s, [0.25, 0.5, 0.75]), [1.5, 2.0, 2.2], rtol=0.02)
    two = sizes((1.0, 4.0))
    assert 0.48 < np.mean(two < 2.0) < 0.52  # as many between 1 and 2 µT as between 2 and 4
    with pytest.raises(ValueError, match="glitch sizes"):
        _model(glitch_ut=(3.0, 2.0))


def test_repeated_reads_repeat_the_last_conversion_in_a_steady_pattern_and_leave_the_rest():
    """A host polling faster than the sensor converts reads the last conversion again, bit for
    bit: at a 24 % share every 4th or 5th read, the phase a function of the seed; the noise,
    wander and glitches are the same draws with or without repeats."""
    sm = _model(repeat_share=0.24, saturation_ut=None, quantum_ut=(0.0, 0.0, 0.0))
    a = np.linspace(0.0, 20.0 * np.pi, 4000)
    u = np.column_stack([0.6 * np.cos(a), 0.6 * np.sin(a), np.full(4000, 0.8)])
    t = np.arange(4000) / 50.0
    m, _ = sm.simulate(u, t, {"current_a": np.zeros(4000)}, seed=3)
    same = np.all(np.diff(m, axis=0) == 0, axis=1)
    assert abs(same.mean() - 0.24) < 0.002
    gaps = np.diff(np.flatnonzero(same))
    assert set(gaps) <= {4, 5}
    fresh, _ = sm.without("repeats").simulate(u, t, {"current_a": np.zeros(4000)}, seed=3)
    assert np.array_equal(m[~np.concatenate([[False], same])], fresh[~np.concatenate([[False], same])])
    other, _ = sm.simulate(u, t, {"current_a": np.zeros(4000)}, seed=4)
    assert not np.array_equal(np.all(np.diff(other, axis=0) == 0, axis=1), same)
    assert "repeats" in sm.effects() and "repeats" not in sm.without("repeats").effects()


def test_repeat_share_is_written_and_an_older_file_reads_as_none():
    d = _model(repeat_share=0.1).to_dict()
    assert d["reads"] == {"repeat_share": 0.1}
    assert SensorModel.from_dict(json.loads(json.dumps(d))).repeat_share == 0.1
    d.pop("reads")
    d["schema"] = "magcal.sensor-model/2"
    assert SensorModel.from_dict(d).repeat_share == 0.0
    with pytest.raises(ValueError, match="repeat_share"):
        _model(repeat_share=1.0)


def test_noise_that_alternates_between_reads_is_drawn_at_its_correlation_and_read_back():
    """A sensor whose noise anti-correlates between successive reads (an AMR bridge flipped
    between reads): the drawn noise has that lag-1 correlation and the model's variance, the
    file keeps it, a fifth-version file is white, and a correlation no moving average of one
    step reaches is refused."""
    m = dataclasses.replace(_model(), noise_lag1=-0.3)
    noise = m.draws(np.arange(200_000) / 50.0, seed=4).noise
    for a in range(3):
        x = noise[:, a]
        assert abs(np.corrcoef(x[1:], x[:-1])[0, 1] + 0.3) < 0.01
        assert abs(np.var(x) - 1.0) < 0.02
    assert SensorModel.from_dict(m.to_dict()).noise_lag1 == -0.3
    clean = SensorModel(calibration=Calibration(offset_ut=[20.0, -30.0, 5.0], field_ut=48.0), noise_ut=(0.3,) * 3,
                        noise_lag1=-0.3, rate_hz=50.0)  # the simulator's own motion, read by read index
    sc = Scenario(physics=Physics(), motion=Motion("sphere", period_s=15.0), seed=2, model=clean)
    e = np.linalg.norm(sc.simulate(20_000).series.field_ut - clean.calibration.offset_ut, axis=1) - 48.0
    assert abs(np.corrcoef(e[1:], e[:-1])[0, 1] + 0.3) < 0.03
    d = m.to_dict()
    d["schema"] = "magcal.sensor-model/5"
    del d["noise_lag1"]
    assert SensorModel.from_dict(d).noise_lag1 == 0.0
    with pytest.raises(ValueError, match="noise_lag1"):
        _model(noise_lag1=0.6)


def test_takes_are_written_drawn_as_a_level_per_take_and_an_older_file_reads_as_one_take():
    """A recording of takes: the file keeps when each take starts and the spread of their
    levels; the twin draws one level of the field's magnitude per take (the same within a take,
    a function of the seed), and the rest of its draws are the model's without takes."""
    from magcal.sim.takes import Takes

    m = _model(takes=Takes(start_s=(2.0, 5.0, 9.0), level_sd_ut=1.5))
    d = json.loads(json.dumps(m.to_dict()))
    assert d["takes"] == {"count": 4, "start_s": [2.0, 5.0, 9.0], "level_sd_ut": 1.5}
    assert SensorModel.from_dict(d).to_dict() == m.to_dict()
    t = np.arange(600) / 50.0
    with_takes, without = m.draws(t, seed=5), m.without("takes").draws(t, seed=5)
    level = with_takes.field_wander_ut - without.field_wander_ut
    take = m.takes.index(t)
    assert [len(np.unique(level[take == k])) for k in range(4)] == [1, 1, 1, 1]
    assert len(np.unique(level)) == 4 and np.array_equal(level, m.draws(t, seed=5).field_wander_ut - without.field_wander_ut)
    assert np.array_equal(with_takes.noise, without.noise) and np.array_equal(with_takes.wander_ut, without.wander_ut)
    assert "takes" in m.effects() and "takes" not in m.without("takes").effects()
    d["schema"] = "magcal.sensor-model/7"
    del d["takes"]
    assert SensorModel.from_dict(d).takes is None
    with pytest.raises(ValueError, match="start_s"):
        Takes(start_s=(5.0, 2.0))
