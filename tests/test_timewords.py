"""A recording without a clock is said in samples (magcal.diagnose.timewords): its t_s is the
sample index, so a diagnosis that says "at 1500.0 s" names a unit the recording never had."""

from __future__ import annotations

import re

import numpy as np

from magcal.core.series import Series
from magcal.diagnose import diagnose, timewords
from magcal.sim.physics import Motion, Physics, Scenario

SECONDS = re.compile(r"\d s\b|\bHz\b")


def test_a_table_without_time_has_its_step_found_as_with_a_clock_and_said_at_a_sample():
    # the same 60 s at 50 Hz, once with its times and once as a bare table of x, y, z: the step
    # search's windows in seconds must not shrink to a few samples when the clock is missing
    sc = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3),
                  motion=Motion("sphere", period_s=20.0), seed=5)
    run = sc.simulate(3000, 50.0).series
    n = len(run.t_s)
    m = run.field_ut + np.outer(np.arange(n) >= 1500, [3.0, -2.0, 2.0])  # a screwdriver put down half way
    steps = []
    for t, clock in ((run.t_s, True), (np.arange(n, dtype=float), False)):
        d = diagnose(Series(t_s=t, field_ut=m, clock=clock)).to_dict()
        (step,) = [x for x in d["findings"] if x["effect"] == "hard_iron_step"]
        steps.append(step)
    timed, bare = steps
    assert abs(bare["where"]["time_s"][0] - 1500) <= 10
    assert np.allclose(bare["params"]["step_ut"], timed["params"]["step_ut"], atol=0.1)
    assert re.search(r"at sample 1[45]\d\d \(±\d+ samples\)", bare["summary"])
    assert re.search(r"at [23]\d\.\d s \(±", timed["summary"])
    said = [x["summary"] for x in d["findings"] + d["limits"]]
    assert not [s for s in said if SECONDS.search(s)]


def test_outside_a_diagnosis_and_with_a_clock_times_are_seconds():
    assert timewords.instant(40.0) == "40.0 s"
    assert timewords.stretch(10.0, 20.5) == "10.0–20.5 s"

    @timewords.in_recording_time
    def said(series):
        return timewords.instant(12.0), timewords.frequency(0.05), timewords.duration(-3.0, "+.2f")

    t = np.arange(10, dtype=float)
    assert said(Series(t_s=t, field_ut=np.zeros((10, 3)), clock=False)) == (
        "sample 12", "0.0500 cycles per sample", "-3 samples")
    assert said(series=Series(t_s=t, field_ut=np.zeros((10, 3)))) == ("12.0 s", "0.050 Hz", "-3.00 s")
    assert timewords.clocked()


def test_the_twins_slow_share_on_a_table_without_time_smooths_over_as_many_samples_as_with_one():
    # the twin's statistics smooth over 1 s and look for a channel within ±2 s: on a bare table
    # read as seconds that was 1 and 2 samples — no smoothing at all (slow_share exactly 1 on the
    # recording and on every twin) and a channel lagging by 30 samples never seen
    from magcal.diagnose.twin import stats as ts

    n = 3000
    rng = np.random.default_rng(4)
    e = rng.standard_normal(n)
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    x = np.roll(e, 30) + 0.3 * rng.standard_normal(n)
    shares, corrs = [], []
    for t, clock in ((np.arange(n) / 50.0, True), (np.arange(n, dtype=float), False)):
        stats, _ = timewords.in_recording_time(
            lambda series: ts.battery(e, u, u * 50.0, series.t_s, {"aux": x}, gain=0.0))(Series(t_s=t, field_ut=u * 50.0, clock=clock))
        shares.append(stats["slow_share"])
        corrs.append(stats["xcorr:aux"])
    timed, bare = shares
    assert timed < 0.1 and 0.5 * timed < bare < 2.0 * timed
    assert min(corrs) > 0.9


def test_the_twins_spectral_slope_on_a_table_without_time_is_read_in_the_same_band_as_with_one():
    # psd_slope reads the residual's spectrum at 0.02–1 Hz; on a bare table that band read as
    # cycles per sample was the white floor above the wander, whatever the wander did
    from magcal.diagnose.twin import stats as ts

    n = 6000
    rng = np.random.default_rng(5)
    walk = np.cumsum(rng.standard_normal(n)) * 0.05  # a random walk: slope −2 at low frequencies
    e = walk - walk.mean() + 0.5 * rng.standard_normal(n)  # white above ~0.3 Hz at 50 Hz
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    slopes = []
    for t, clock in ((np.arange(n) / 50.0, True), (np.arange(n, dtype=float), False)):
        stats, _ = timewords.in_recording_time(
            lambda series: ts.battery(e, u, u * 50.0, series.t_s, {}, gain=0.0))(Series(t_s=t, field_ut=u * 50.0, clock=clock))
        slopes.append(stats["psd_slope"])
    timed, bare = slopes
    assert timed < -1.0 and abs(bare - timed) < 0.5
