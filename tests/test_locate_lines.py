"""narrowband_line: a sinusoid added to the sensor axes, found in frequency, sized and taken out."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcal.core.sample import UT_PER_COUNT, asa_gain
from magcal.diagnose.locate import lines
from magcal.diagnose.locate.base import Kind, Residual
from magcal.diagnose.locate.step import floor_of
from magcal.fit import fit_calibration
from magcal.sim.physics import Motion, Physics, Scenario

DATA = Path(__file__).parent / "data"


def _sim(seed, rate_hz=50.0, n=2000, motion="sphere", noise_ut=0.4, jitter_s=0.0):
    sc = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=noise_ut), motion=Motion(motion), seed=seed)
    k = np.arange(n)
    t = np.sort(k / rate_hz + np.random.default_rng(seed).normal(0.0, jitter_s, n))
    m, _ = sc.field_ut(t, k)
    raw, _ = sc.to_counts(m)
    return t, raw * UT_PER_COUNT * np.array([asa_gain(a) for a in sc.physics.asa])


def _search(t, m, floor_ut=None):
    res = Residual(t, m, fit_calibration(m).calibration, 0.4, floor_ut or floor_of(m), {})
    return lines.search(res)


def _line(t, amp_ut, f_hz, phase=0.7):
    return np.outer(np.cos(2 * np.pi * f_hz * t + phase), amp_ut)


def _real_tilt():
    a = np.loadtxt(DATA / "hmc5883l_sunsided_tilt_sphere_counts.csv", delimiter=",", skiprows=1)
    return a[:, 0], a[:, 1:4] * 100.0 / 1090.0  # counts at 1090 LSB/G → µT


def test_mains_hum_aliased_by_the_sample_clock_is_found_sized_and_named():
    # 50 Hz mains sampled by a 47.6 Hz clock (with timestamp jitter) shows at 2.4 Hz
    t, m = _sim(3, rate_hz=47.6, jitter_s=0.3e-3)
    floor = floor_of(m)
    found = _search(t, m + _line(t, (3 * floor, 0.0, 0.0), 50.0))
    assert len(found) == 1
    x = found[0]
    assert x.effect == "narrowband_line" and x.kind is Kind.PHYSICS
    assert abs(x.where["frequency_hz"] - 2.4) < 0.02 * 2.4
    assert x.where["axis"] == "x"
    assert abs(x.params["amplitude_ut"][0] - 3 * floor) < 0.15 * 3 * floor
    assert x.params["mains_hz"] == 50.0
    assert "50 Hz mains aliased by the 47.6 Hz sample clock" in x.summary


def test_two_lines_on_a_direction_are_both_found_and_removed():
    t, m = _sim(4, rate_hz=100.0, n=3000, motion="tilt", noise_ut=1.0, jitter_s=0.5e-3)
    floor = floor_of(m)
    d = np.array([0.6, -0.8, 0.0])
    injected = _line(t, 4 * floor * d, 13.7) + _line(t, (0.0, 0.0, 2 * floor), 31.0, 2.0)
    dirty = m + injected
    found = _search(t, dirty)
    freqs = sorted(x.where["frequency_hz"] for x in found)
    assert np.allclose(freqs, [13.7, 31.0], rtol=0.02)
    by_f = {round(x.where["frequency_hz"]): x for x in found}
    assert sorted(by_f[14].where["axis"]) == ["x", "y"]
    assert abs(np.dot(by_f[14].where["direction"], d)) > 0.98
    assert by_f[31].where["axis"] == "z"
    cleaned = dirty
    for x in found:
        cleaned = lines.remove(cleaned, t, {}, x)
    # what is left of the lines is the estimate's scatter (noise 1 µT, tilts only): under 15 %
    assert np.sqrt(np.mean((cleaned - m) ** 2)) < 0.15 * np.sqrt(np.mean(injected**2))


@pytest.mark.parametrize("motion,seed", [("sphere", 5), ("tilt", 6)])
def test_nothing_claimed_on_clean_simulations(motion, seed):
    t, m = _sim(seed, motion=motion)
    assert _search(t, m) == ()


def test_found_in_a_real_recording_and_nothing_claimed_without_it():
    # a hand-held HMC5883L recording with uneven (bursty) timestamps and real slow wander
    t, m = _real_tilt()
    floor = floor_of(m)
    assert _search(t, m, floor) == ()
    found = _search(t, m + _line(t, (0.0, 3 * floor, 0.0), 23.3), floor)
    assert len(found) == 1
    assert abs(found[0].where["frequency_hz"] - 23.3) < 0.02 * 23.3
    assert found[0].where["axis"] == "y"
    assert abs(found[0].params["amplitude_ut"][1] - 3 * floor) < 0.15 * 3 * floor
    assert found[0].params["mains_hz"] is None


def test_remove_rejects_samples_of_the_wrong_shape():
    t, m = _sim(7, n=400)
    x = lines.search(Residual(t, m + _line(t, (5.0, 0.0, 0.0), 7.0), fit_calibration(m).calibration, 0.4, 0.4))[0]
    with pytest.raises(ValueError, match="m_ut must be"):
        lines.remove(m[:, :2], t, {}, x)


def test_a_misfit_at_the_motions_own_turn_rate_is_set_aside_not_claimed():
    # flat turns at a steady rate: a hard-iron error of 1.5 µT makes the radial residual a pure
    # sinusoid at the turn rate — a function of the direction, so not a line
    sc = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0)), motion=Motion("yaw", period_s=8.0), seed=9)
    run = sc.simulate(1500, 50.0)
    cal = replace(run.truth, offset_ut=np.asarray(run.truth.offset_ut) + (1.5, 0.0, 0.0))
    res = Residual(run.series.t_s, run.series.field_ut, cal, 0.4, 0.5, {})
    found, set_aside, _ = lines.find_lines(res)
    assert found == [] and len(set_aside) == 1
    assert lines.search(res) == ()


def test_a_clock_that_repeats_its_stamps_still_gives_the_line():
    t, m = _sim(8, n=1500)
    floor = floor_of(m)
    # a 25 Hz clock stamping 50 Hz samples: each stamp twice (a slow line, so that the stamps'
    # 40 ms coarseness costs it little phase)
    stamped = np.floor(t * 25.0) / 25.0
    found = _search(stamped, m + _line(t, (0.0, 0.0, 4 * floor), 1.3), floor)
    assert len(found) == 1 and found[0].where["axis"] == "z"
    assert abs(found[0].where["frequency_hz"] - 1.3) < 0.02 * 1.3


def test_mains_at_half_the_sample_clock_lands_on_nyquist_and_is_found():
    t, m = _sim(10, rate_hz=100.0, n=2000)
    floor = floor_of(m)
    found = _search(t, m + _line(t, (0.0, 2 * floor, 0.0), 50.0, 0.4), floor)
    assert len(found) == 1 and found[0].where["axis"] == "y"
    assert abs(found[0].where["frequency_hz"] - 50.0) < 0.02 * 50.0
    assert found[0].params["mains_hz"] == 50.0 and found[0].params["mains_harmonic"] == 1


def test_a_search_stopped_at_its_line_limit_says_more_may_remain():
    t, m = _sim(21, n=3000)
    freqs = (3.1, 5.3, 7.7, 11.9, 17.3)  # one more than the search takes
    amps = (6.0, 5.5, 5.0, 4.5, 4.0)
    five = m + sum(_line(t, (a, 0.5 * a, 0.0), f) for a, f in zip(amps, freqs))
    found = _search(t, five)
    assert len(found) == lines.MAX_LINES
    left = found[-1].evidence["next_candidate_beyond_max_lines_hz"]
    taken = [x.where["frequency_hz"] for x in found]
    missing = [f for f in freqs if min(abs(f - g) for g in taken) > 0.02 * f]
    assert len(missing) == 1 and abs(left - missing[0]) < 0.02 * missing[0]
    assert "more lines may remain" in found[-1].summary
    assert all(x.evidence["next_candidate_beyond_max_lines_hz"] is None for x in found[:-1])
    three = m + sum(_line(t, (a, 0.5 * a, 0.0), f) for a, f in zip(amps[:3], freqs[:3]))
    assert all("more lines may remain" not in x.summary for x in _search(t, three))


def _lagged_square_current(t, period_s=9.0, tau_s=0.6, seed=0):
    """A current switched on and off every ``period_s`` (logged, with a little noise) and what it
    reaches the sensor as: the same through a first-order lag of ``tau_s``."""
    cur = 8.0 * (np.sin(2 * np.pi * t / period_s + 0.4) > 0.2) + 0.2 * np.random.default_rng(seed).standard_normal(len(t))
    lagged = np.zeros_like(cur)
    for i in range(1, len(t)):
        a = np.exp(-(t[i] - t[i - 1]) / tau_s)
        lagged[i] = a * lagged[i - 1] + (1 - a) * cur[i]
    return cur, lagged


def test_a_logged_currents_harmonics_are_the_currents_structure_not_free_lines():
    # a square-wave current through a lag puts lines at 1/9 Hz and its harmonics into the residual of
    # a calibration without it; the logged current carries the same lines: they are said as its
    t, m = _sim(6, rate_hz=25.0, n=3000)
    cur, lagged = _lagged_square_current(t)
    dirty = m + np.outer(lagged, (0.25, -0.1, 0.2))
    res = Residual(t, dirty, fit_calibration(dirty).calibration, 0.4, floor_of(dirty), {"current_a": cur})
    found = lines.search(res)
    assert found and not [x for x in found if x.effect == "narrowband_line"]
    (said,) = found
    assert said.kind is Kind.REMAINDER and said.where["channel"] == "current_a"
    harmonics = np.asarray(said.where["frequency_hz"]) * 9.0
    assert np.allclose(harmonics, np.round(harmonics), atol=0.05) and 1 in np.round(harmonics)


def test_a_line_beside_a_logged_current_is_still_found_as_a_line():
    # the current's own lines are its; a hum at a frequency the current does not carry is a line
    t, m = _sim(6, rate_hz=25.0, n=3000)
    cur, lagged = _lagged_square_current(t)
    floor = floor_of(m)
    dirty = m + np.outer(lagged, (0.25, -0.1, 0.2)) + _line(t, (0.0, 3 * floor, 0.0), 7.28)
    res = Residual(t, dirty, fit_calibration(dirty).calibration, 0.4, floor_of(dirty), {"current_a": cur})
    free = [x for x in lines.search(res) if x.effect == "narrowband_line"]
    assert len(free) == 1 and abs(free[0].where["frequency_hz"] - 7.28) < 0.02 * 7.28 and free[0].where["axis"] == "y"


@pytest.mark.parametrize("size", [7.0, 15.0, 30.0])
def test_a_hum_whose_load_changes_is_still_a_line_however_strong(size):
    # 60 Hz mains seen at 10 Hz by a 50 Hz clock, its amplitude following a load that swings ±30 %
    # once over the take: a steady frequency whose slow sidebands sit beside it, a line at any size
    # (before: set aside as broad at 7×, 15× and 30× the floor — its statistic, read against the
    # local level it raises itself, stopped growing while the ring it leaves grew with its square)
    t, m = _sim(5, rate_hz=50.0, n=4000, jitter_s=0.2e-3)
    floor = floor_of(m)
    span = t[-1] - t[0]
    load = 1.0 + 0.3 * np.sin(2 * np.pi * (t - t[0]) / span + 0.4)
    d = np.array([0.48, -0.6, 0.64])
    found = _search(t, m + _line(t, size * floor * np.sqrt(2) * d, 60.0) * load[:, None])
    hz = [x.where["frequency_hz"] for x in found if x.effect == "narrowband_line"]
    assert any(abs(f - 10.0) < 0.02 * 10.0 for f in hz), hz
