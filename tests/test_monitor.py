"""The drift test: quiet on a calibration that fits, loud soon after a new hard iron, at about
the configured false-alarm rate, and resumable from its JSON state."""

import json
from dataclasses import replace

import numpy as np
import pytest

from magcal.fit import fit_calibration
from magcal.logic.monitor import DriftMonitor, Phase, WindowTest
from magcal.sim.physics import Motion, demo_scenario


@pytest.fixture(scope="module")
def calibrated():
    sc = demo_scenario(5)
    cal = fit_calibration(sc.simulate(6000, 100.0).series.field_ut, model="auto", outliers=True).calibration
    return sc, cal


def _stream(sc, n, t0_s):
    return sc.simulate(n, 100.0, t0_s=t0_s).series.field_ut


def test_good_calibration_raises_about_alpha_alarms(calibrated):
    sc, cal = calibrated
    mon = DriftMonitor(cal, window=400, alpha=0.01)
    verdicts = mon.add(_stream(sc, 400 * 208, 50.0))
    tests = [v for v in verdicts if v.phase is Phase.TEST]
    assert len(tests) == 200
    # 200 tests at α = 1 %: expect 2; Poisson(2) exceeds 7 with probability < 0.2 %
    assert mon.alarms <= 7
    p = np.array([v.p_value for v in tests])
    assert 0.2 < np.mean(p) < 0.8  # p-values spread over (0, 1), not piled at 0
    sigma, tau = mon.noise()
    assert 0.3 < sigma < 0.6  # the simulated noise is 0.4 µT (plus quantisation)
    assert tau >= 1.0


@pytest.mark.parametrize("motion", ["sphere", "tilt", "still"])
def test_new_hard_iron_is_detected_within_two_windows(calibrated, motion):
    sc, cal = calibrated
    sc = replace(sc, motion=Motion(motion)) if motion != "sphere" else sc
    mon = DriftMonitor(cal, window=500, alpha=0.001)
    before = mon.add(_stream(sc, 4500, 30.0))
    assert not any(v.drifted for v in before)
    payload = sc.with_physics(hard_iron_ut=tuple(np.add(sc.physics.hard_iron_ut, (1.5, -1.0, 0.5))))
    after = mon.add(_stream(payload, 1000, 60.0))
    assert any(v.drifted for v in after)
    assert mon.drifted and mon.first_alarm_window <= 11


def test_shift_estimate_points_at_the_new_hard_iron(calibrated):
    sc, cal = calibrated
    mon = DriftMonitor(cal, window=1000, alpha=0.001)
    mon.add(_stream(sc, 8000, 30.0))
    delta = np.array([3.0, -2.0, 1.0])
    payload = sc.with_physics(hard_iron_ut=tuple(np.add(sc.physics.hard_iron_ut, delta)))
    v = mon.add(_stream(payload, 1000, 34.0))[-1]  # a stretch of motion seen in the baseline
    assert v.drifted
    assert np.linalg.norm(np.array(v.estimated_shift_ut) - delta) < 0.5


def test_state_round_trip_gives_the_same_verdicts(calibrated):
    sc, cal = calibrated
    data = _stream(sc, 4333, 10.0)
    a = DriftMonitor(cal, window=300, alpha=0.01)
    a.add(data[:2777])
    b = DriftMonitor.from_state(json.loads(json.dumps(a.to_state())))
    va = a.add(data[2777:])
    vb = b.add(data[2777:])
    assert [v.to_dict() for v in va] == [v.to_dict() for v in vb]
    assert b.status() == a.status()


def test_bad_settings_are_refused(calibrated):
    _, cal = calibrated
    with pytest.raises(ValueError, match="window"):
        DriftMonitor(cal, window=10)
    with pytest.raises(ValueError, match="alpha"):
        DriftMonitor(cal, alpha=0.7)
    with pytest.raises(ValueError, match="malformed"):
        DriftMonitor.from_state({"calibration": cal.to_dict()})


@pytest.mark.slow
def test_a_sensor_whose_offset_wanders_raises_about_alpha_alarms(calibrated):
    """A real sensor's offset wanders slowly (an OU process, as fitted to real recordings): that
    is the sensor's normal state, not a new hard iron, and must not raise alarms beyond alpha."""
    import dataclasses

    from magcal.sim.wander import WanderComponent

    sc, cal = calibrated
    sensor = dataclasses.replace(sc.sensor, calibration=cal, noise_ut=(0.25,) * 3,
                                 wander=(WanderComponent(0.25, 40.0), WanderComponent(0.1, 4.0)))
    verdicts = _tests_at_one_percent(sc, cal, sensor, (21, 22))
    assert len(verdicts) == 200
    # 200 tests at α = 1 %: expect 2; Poisson(2) exceeds 7 with probability < 0.2 %
    assert sum(v.drifted for v in verdicts) <= 7


def _tests_at_one_percent(sc, cal, sensor, seeds):
    """The test verdicts of a 1 % monitor over 100 test windows of ``sensor`` per seed."""
    import dataclasses

    out = []
    for seed in seeds:
        mon = DriftMonitor(cal, window=400, alpha=0.01)
        s = dataclasses.replace(sc, model=sensor, seed=seed).simulate(400 * 108, 100.0, t0_s=50.0).series
        out += [v for v in mon.add(s.field_ut) if v.phase is Phase.TEST]
    return out


def _wandering(sc, cal):
    import dataclasses

    from magcal.sim.wander import WanderComponent

    return dataclasses.replace(sc.sensor, calibration=cal, noise_ut=(0.25,) * 3,
                               wander=(WanderComponent(0.25, 40.0), WanderComponent(0.1, 4.0),
                                       WanderComponent(sigma_ut=(0.5,) * 3, band_hz=(0.002, 0.01), frame="field")))


@pytest.mark.slow
def test_the_field_magnitude_wandering_is_not_a_new_hard_iron(calibrated):
    """The local field's magnitude wanders (iron nearby moves): |h| − r moves by the same amount
    whichever way the board faces — a change of radius, which the hard-iron test leaves free."""
    sc, cal = calibrated
    verdicts = _tests_at_one_percent(sc, cal, _wandering(sc, cal), (31, 32))
    assert len(verdicts) == 200 and all(v.test is WindowTest.HARD_IRON for v in verdicts)
    assert sum(v.drifted for v in verdicts) <= 7  # Poisson(2) exceeds 7 with probability < 0.2 %


@pytest.mark.parametrize("motion", ["sphere", "still"])
def test_a_new_hard_iron_is_caught_on_a_wandering_sensor(calibrated, motion):
    """The spread the monitor allows for the wander must not hide a real offset step."""
    import dataclasses

    sc, cal = calibrated
    sensor = _wandering(sc, cal)
    sc = dataclasses.replace(sc, model=sensor, seed=41, motion=Motion(motion))
    mon = DriftMonitor(cal, window=500, alpha=0.001)
    before = mon.add(_stream(sc, 500 * 20, 30.0))
    assert mon.phase is Phase.TEST and not any(v.drifted for v in before)
    delta = np.array([2.0, -1.5, 1.0])
    m = _stream(sc, 1000, 130.0) + delta  # a payload: every reading moves by δ
    after = mon.add(m)
    assert any(v.drifted for v in after)  # within the two windows after it
    assert next(v for v in after if v.drifted).test is (WindowTest.HARD_IRON if motion == "sphere" else WindowTest.COMBINED)


def test_a_state_of_the_first_version_relearns_its_baseline(calibrated):
    """A state written before the hard-iron reference existed is not refused (the daemon would
    lose its whole resume state): the monitor keeps its counts and learns its baseline again."""
    sc, cal = calibrated
    a = DriftMonitor(cal, window=300, alpha=0.01)
    a.add(_stream(sc, 300 * 12, 10.0))
    old = json.loads(json.dumps(a.to_state()))
    del old["version"]
    b = DriftMonitor.from_state(old)
    assert b.phase is Phase.BASELINE and b.windows == a.windows and b.alarms == a.alarms
    assert [v.phase for v in b.add(_stream(sc, 300 * 9, 60.0))] == [Phase.BASELINE] * 8 + [Phase.TEST]


def _band_wander(rng, t_s, sigma_ut, band_hz=(0.03, 0.09), k=40):
    """An offset wander confined to a narrow band of slow frequencies (as learned from a
    quadcopter's QMC5883L): a sum of ``k`` sines of random frequency and phase per axis."""
    f = rng.uniform(*band_hz, size=(k, 1, 1))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(k, 1, 3))
    at = 2.0 * np.pi * f[:, 0, 0] * t_s[:, None]  # sin(a + φ) = sin a cos φ + cos a sin φ, summed over the k as products
    return sigma_ut * np.sqrt(2.0 / k) * (np.sin(at) @ np.cos(phase[:, 0]) + np.cos(at) @ np.sin(phase[:, 0]))


@pytest.mark.slow
def test_a_wander_that_pauses_and_resumes_raises_about_alpha_alarms(calibrated):
    """A narrow-band wander has calm stretches. The spread the monitor allows must outlast
    one — a spread as short-lived as the reference read "no wander" in the calm, and the
    wander's return then alarmed at many times the stated rate."""
    sc, cal = calibrated
    active, calm, back = 48, 30, 40  # windows of 500 samples
    late = []
    for seed in range(1, 11):
        rng = np.random.default_rng(seed)
        s = replace(sc, seed=seed, motion=Motion("sphere", period_s=20.0)).simulate(
            500 * (active + calm + back), 100.0, t0_s=50.0).series
        envelope = np.ones(len(s.t_s))
        envelope[500 * active: 500 * (active + calm)] = 0.0
        envelope = np.convolve(envelope, np.ones(500) / 500, mode="same")  # it fades out and in
        m = s.field_ut + envelope[:, None] * _band_wander(rng, s.t_s - s.t_s[0], 0.2)
        verdicts = DriftMonitor(cal, window=500, alpha=0.001).add(m)
        assert not any(v.drifted for v in verdicts[:active])
        late += verdicts[active + calm:]
    assert len(late) == 400
    # 400 tests at α = 0.1 %: expect 0.4; Poisson(0.4) exceeds 2 with probability < 0.8 %
    assert sum(v.drifted for v in late) <= 2
