"""magcal diagnose: each effect found by name with its parameters, clean recordings silent,
the JSON shape of the command, the report files, outlier indices as file rows."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stdout

import numpy as np
import pytest

from magcal.cli import main
from magcal.core.series import Series
from magcal.diagnose import diagnose
from magcal.recordings.table import save_csv
from magcal.sim.physics import Current, Motion, Physics, Scenario, Temperature

N = 5000
HARD = (21.0, -33.0, 8.0)


def _sim(seed, n=N, motion=Motion("sphere", period_s=20.0), temperature=Temperature(), current=Current(), **phys):
    sc = Scenario(physics=Physics(hard_iron_ut=HARD, **phys), motion=motion, temperature=temperature, current=current, seed=seed)
    return sc.simulate(n, 50.0)


def _finding(d, effect):
    found = [f for f in d.findings if f.effect == effect]
    assert found, f"{effect} not found; findings: {d.effects}"
    return found[0]


@pytest.mark.slow
@pytest.mark.parametrize(
    "seed,kwargs",
    [
        (101, {}),
        (102, {"temperature": Temperature(swing_c=20.0, period_s=60.0), "current": Current(level_a=2.0)}),
        (103, {"motion": Motion("tilt", max_tilt_deg=35.0)}),
        (104, {"noise_ut": 1.0}),
    ],
    ids=["sphere", "with-channels", "partial-coverage", "noisy"],
)
def test_clean_recordings_have_no_findings(seed, kwargs):
    run = _sim(seed, **kwargs)
    d = diagnose(run.series)
    assert d.effects == []
    assert np.allclose(d.final.offset_ut, HARD, atol=0.3)


@pytest.mark.slow
def test_soft_iron_found_and_modelled():
    a = ((1.012, 0.004, 0.0), (0.004, 0.993, -0.003), (0.0, -0.003, 0.995))
    run = _sim(111, distortion=a)
    d = diagnose(run.series)
    assert d.effects == ["soft_iron"]
    w = np.array(_finding(d, "soft_iron").params["soft_iron"])
    truth = np.linalg.inv(np.array(a))
    truth *= 3.0 / np.trace(truth)
    assert np.allclose(w, truth, atol=2e-3)
    assert d.final_heldout_rms_ut < d.baseline_heldout_rms_ut


@pytest.mark.slow
def test_temperature_drift_found_with_its_coefficient():
    k = np.array([0.07, -0.05, 0.04])
    run = _sim(112, temperature=Temperature(swing_c=20.0, period_s=60.0), temp_coef_ut_per_c=tuple(k))
    d = diagnose(run.series)
    assert d.effects == ["temperature_drift"]
    f = _finding(d, "temperature_drift")
    assert f.params["channel"] == "temp_c"
    assert np.linalg.norm(np.array(f.params["coef_ut_per_unit"]) - k) < 0.3 * np.linalg.norm(k)
    assert d.final_heldout_rms_ut < d.baseline_heldout_rms_ut


@pytest.mark.slow
def test_current_interference_found_on_an_intermittent_channel():
    k = np.array([0.4, 0.3, -0.2])
    run = _sim(113, current=Current(level_a=2.0), current_coef_ut_per_a=tuple(k))
    d = diagnose(run.series)
    assert d.effects == ["current_interference"]
    f = _finding(d, "current_interference")
    assert np.linalg.norm(np.array(f.params["coef_ut_per_unit"]) - k) < 0.3 * np.linalg.norm(k)


@pytest.mark.slow
def test_any_other_channel_is_a_candidate_covariate():
    k = np.array([0.3, -0.3, 0.2])
    run = _sim(114, current=Current(level_a=2.0), current_coef_ut_per_a=tuple(k))
    s = run.series
    renamed = type(s)(t_s=s.t_s, field_ut=s.field_ut, channels={"throttle": s.channels["current_a"]})
    d = diagnose(renamed)
    assert d.effects == ["covariate:throttle"]
    assert _finding(d, "covariate:throttle").params["channel"] == "throttle"


@pytest.mark.slow
def test_time_drift_found():
    k = np.array([0.012, -0.006, 0.005])
    run = _sim(115, drift_ut_per_s=tuple(k))
    d = diagnose(run.series)
    assert d.effects == ["time_drift"]
    f = _finding(d, "time_drift")
    assert np.linalg.norm(np.array(f.params["coef_ut_per_unit"]) - k) < 0.3 * np.linalg.norm(k)


@pytest.mark.slow
def test_monotone_warm_up_is_reported_as_confounded_not_guessed():
    run = _sim(116, drift_ut_per_s=(0.01, 0.0, -0.008))
    s = run.series
    warm = 20.0 + 15.0 * (s.t_s / s.t_s[-1])  # rises with time only
    d = diagnose(type(s)(t_s=s.t_s, field_ut=s.field_ut, channels={"temp_c": warm}))
    assert d.effects == ["time_drift"]
    f = _finding(d, "time_drift")
    assert f.evidence["confounded_with"] == "temp_c"
    assert "cannot be told apart" in f.summary


def test_glitches_found_including_sideways_ones():
    run = _sim(117, glitch_rate=0.006)
    d = diagnose(run.series)
    assert d.effects == ["outliers"]
    got = set(_finding(d, "outliers").params["indices"])
    truth = set(int(i) for i in run.glitch_idx)
    tp = len(got & truth)
    f1 = 2 * tp / (len(got) + len(truth))
    assert f1 >= 0.9


@pytest.mark.slow
def test_a_pair_of_effects_is_found_together():
    run = _sim(118, temperature=Temperature(swing_c=18.0, period_s=60.0), temp_coef_ut_per_c=(0.06, 0.05, -0.04), glitch_rate=0.004)
    d = diagnose(run.series)
    assert sorted(d.effects) == ["outliers", "temperature_drift"]


def _cli_json(argv) -> dict:
    buf = io.StringIO()
    with redirect_stdout(buf):
        assert main(argv) == 0
    return json.loads(buf.getvalue())


@pytest.mark.slow
def test_json_output_has_the_documented_shape(tmp_path):
    run = _sim(119, temperature=Temperature(swing_c=20.0, period_s=60.0), temp_coef_ut_per_c=(0.08, -0.04, 0.05))
    path = tmp_path / "rec.csv"
    save_csv(run.series, path)
    d = _cli_json(["diagnose", str(path), "--json"])
    assert d["n_samples"] == N
    assert d["baseline"]["model"] == "sphere"
    for part in ("baseline", "final"):
        assert d[part]["rms_ut"] > 0 and d[part]["heldout_rms_ut"] > 0
    assert [f["effect"] for f in d["findings"]] == ["temperature_drift"]
    f = d["findings"][0]
    assert set(f) == {"effect", "summary", "where", "evidence", "params"}
    assert f["params"]["channel"] == "temp_c" and len(f["params"]["coef_ut_per_unit"]) == 3
    cal = d["calibration"]
    assert len(cal["offset_ut"]) == 3 and np.array(cal["soft_iron"]).shape == (3, 3)
    assert cal["reference"]["current_a"] == 0.0 and "temp_c" in cal["reference"]
    # a calibrated sample per the documented formula lies on the sphere of radius field_ut
    s = run.series
    k = np.array(cal["coef_ut_per_unit"]["temp_c"])
    h = (s.field_ut - cal["offset_ut"] - np.outer(s.channels["temp_c"] - cal["reference"]["temp_c"], k)) @ np.array(cal["soft_iron"]).T
    assert np.sqrt(np.mean((np.linalg.norm(h, axis=1) - cal["field_ut"]) ** 2)) < 0.5


@pytest.mark.slow
def test_outlier_indices_are_data_rows_of_the_file(tmp_path):
    run = _sim(120, glitch_rate=0.006)
    s = run.series
    path = tmp_path / "rec.csv"
    lines = ["# a comment line before the header", "t,mx,my,mz,valid"]
    # three flagged rows first: they shift positions in the analysed series but not file rows
    lines += ["0.0,0,0,0,0"] * 3
    for t, (x, y, z) in zip(s.t_s + 0.06, s.field_ut):
        lines.append(f"{float(t)!r},{float(x)!r},{float(y)!r},{float(z)!r},1")
    path.write_text("\n".join(lines) + "\n")
    d = _cli_json(["diagnose", str(path), "--json"])
    rows = set(d["findings"][0]["params"]["indices"])
    truth = {int(i) + 3 for i in run.glitch_idx}
    assert d["findings"][0]["effect"] == "outliers"
    assert len(rows & truth) >= 0.9 * len(truth) and len(rows - truth) <= 1


@pytest.mark.slow
def test_report_writes_pictures_and_a_page(tmp_path):
    run = _sim(121, temperature=Temperature(swing_c=20.0, period_s=60.0), temp_coef_ut_per_c=(0.08, -0.04, 0.05), glitch_rate=0.003)
    path = tmp_path / "rec.csv"
    save_csv(run.series, path)
    out = tmp_path / "report"
    _cli_json(["diagnose", str(path), "--json", "--report", str(out)])
    for name in ("directions.png", "time.png", "channels.png", "heldout.png", "coverage.png", "magnitude.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10000
    page = (out / "index.html").read_text()
    assert "temperature_drift" in page and all(n in page for n in ("directions.png", "heldout.png"))
    assert "Read as: field from mx,my,mz in µT; time from t (s); channels temp_c" in page


def test_unreadable_or_too_short_input_is_a_clear_error(tmp_path, capsys):
    path = tmp_path / "short.csv"
    path.write_text("t,mx,my,mz\n0,1,2,3\n1,2,3,4\n")
    assert main(["diagnose", str(path)]) == 3  # read, and too few to diagnose: the data did not pass
    assert "at least" in capsys.readouterr().err


def _wandering(run, seed, amp_ut=0.6):
    """The recording with a slow random offset wander added (a few smooth components over its
    length, ``amp_ut`` peak per axis), as real recordings show."""
    s = run.series
    rng = np.random.default_rng(seed)
    tau = (s.t_s - s.t_s[0]) / np.ptp(s.t_s)
    w = np.zeros((len(tau), 3))
    for f in (0.5, 1.0, 1.7, 2.6):
        w += np.sin(2 * np.pi * f * tau[:, None] + rng.uniform(0, 2 * np.pi, 3)) * rng.uniform(0.3, 1.0, 3) / f
    w *= amp_ut / np.max(np.abs(w), axis=0)
    return Series(t_s=s.t_s, field_ut=s.field_ut + w, channels=s.channels)


@pytest.mark.slow
def test_intermittent_current_found_through_slow_wander():
    k = np.array([0.35, -0.3, 0.2])
    run = _sim(131, current=Current(level_a=2.0, segment_s=4.0), current_coef_ut_per_a=tuple(k))
    d = diagnose(_wandering(run, 131))
    assert "current_interference" in d.effects
    coef = np.array(_finding(d, "current_interference").params["coef_ut_per_unit"])
    assert np.linalg.norm(coef - k) <= 0.3 * np.linalg.norm(k)


@pytest.mark.slow
def test_slow_unrelated_temperature_is_not_credited_with_wander():
    run = _sim(132, temperature=Temperature(swing_c=20.0, period_s=80.0))
    d = diagnose(_wandering(run, 132, amp_ut=0.8))
    assert "temperature_drift" not in d.effects


@pytest.mark.slow
def test_wander_alone_is_not_reported_as_drift_or_current():
    run = _sim(133, current=Current(level_a=2.0, segment_s=4.0))
    d = diagnose(_wandering(run, 133, amp_ut=0.8))
    assert not {"time_drift", "current_interference"} & set(d.effects)


def _glitch_f1(d, truth):
    got = set(_finding(d, "outliers").params["indices"]) if "outliers" in d.effects else set()
    return 2 * len(got & truth) / max(len(got) + len(truth), 1)


def test_glitches_beside_gaps_in_the_timestamps_are_found():
    # a logger that drops samples: every glitch sits just after a gap of 10–20 sample periods,
    # so the prediction of the sample before it reaches across the gap and is poor
    run = _sim(131)
    rng = np.random.default_rng(131)
    starts = np.arange(200, N - 200, 150)
    drop = np.concatenate([np.arange(a, a + rng.integers(10, 21)) for a in starts])
    keep = np.setdiff1d(np.arange(N), drop)
    s = run.series.take(keep)
    m = s.field_ut.copy()
    pos = np.searchsorted(keep, starts) + 1  # the second sample after each gap
    d3 = rng.standard_normal((len(pos), 3))
    m[pos] += 8.0 * d3 / np.linalg.norm(d3, axis=1, keepdims=True)
    d = diagnose(Series(t_s=s.t_s, field_ut=m))
    assert _glitch_f1(d, set(int(i) for i in pos)) >= 0.9


def test_glitches_are_found_from_the_field_magnitude_when_fast_motion_hides_the_jump():
    # a quick wave at a low sample rate: the 3-vector moves several µT between samples, so its
    # own innovations are large, but |m| stays smooth and shows each jump's radial part
    sc = Scenario(physics=Physics(hard_iron_ut=HARD, noise_ut=0.2), motion=Motion("sphere", period_s=1.5), seed=132)
    run = sc.simulate(3000, 10.0)
    rng = np.random.default_rng(132)
    pos = rng.choice(np.arange(10, 2990), 20, replace=False)
    m = run.series.field_ut.copy()
    h = m - np.asarray(HARD)
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    m[pos] += 6.0 * u[pos] * rng.choice([-1.0, 1.0], (20, 1))
    d = diagnose(Series(t_s=run.series.t_s, field_ut=m))
    assert _glitch_f1(d, set(int(i) for i in pos)) >= 0.9


def test_soft_iron_on_a_short_single_sweep_is_found_where_it_can_be_tested_and_the_rest_named():
    # 30 s, one sweep of the sphere: every direction is visited once, so most soft-iron
    # directions cannot be told apart from a slow wander in time; the two that can carry the
    # 2 % gain error plainly, so soft iron is found there and fitted along every direction the
    # motion determines, and the limit says which part could not be tested
    distortion = ((1.02, 0.0, 0.0), (0.0, 0.985, 0.0), (0.0, 0.0, 0.995))
    d = diagnose(_sim(144, n=1500, distortion=distortion).series)
    assert "soft_iron" in d.effects
    (limit,) = [x for x in d.to_dict()["limits"] if x["effect"] == "soft_iron"]
    assert limit["suspected"] is False
    assert 0 < limit["identifiable_directions"] < 5 and limit["determined_directions"] == 5
    assert "may hold slow wander as much as soft iron" in limit["summary"]
    assert d.final.rms_ut < 1.1 * d.simulated_rms_ut


def test_soft_iron_on_a_very_short_sweep_is_named_as_suspected_not_silently_dropped():
    # 8 s: no soft-iron direction can be told apart from a slow wander in time, and the sphere
    # is visibly worse than the noise
    distortion = ((1.02, 0.0, 0.0), (0.0, 0.985, 0.0), (0.0, 0.0, 0.995))
    d = diagnose(_sim(144, n=400, distortion=distortion).series)
    assert "soft_iron" not in d.effects
    (limit,) = [x for x in d.to_dict()["limits"] if x["effect"] == "soft_iron"]
    assert limit["suspected"] is True
    assert "suspected but not identifiable" in limit["summary"]
    assert limit["identifiable_directions"] < 5

    clean = diagnose(_sim(144, n=400).series).to_dict()["limits"]
    assert not any(x["suspected"] for x in clean)


def test_a_well_covered_recording_states_no_limits():
    assert diagnose(_sim(142).series).to_dict()["limits"] == []


def test_the_text_summary_does_not_call_a_suspect_recording_explained(tmp_path, capsys):
    distortion = ((1.02, 0.0, 0.0), (0.0, 0.985, 0.0), (0.0, 0.0, 0.995))
    path = tmp_path / "short.csv"
    save_csv(_sim(144, n=400, distortion=distortion).series, path)
    assert main(["diagnose", str(path)]) == 0
    out = capsys.readouterr().out
    assert "explains the recording" not in out
    assert "limit       soft_iron: Soft iron is suspected but not identifiable" in out


@pytest.mark.parametrize("seed", [151, 152, 153])
def test_a_simulated_recording_without_wander_states_none(seed):
    limits = diagnose(_sim(seed, temperature=Temperature(swing_c=20.0, period_s=60.0)).series).to_dict()["limits"]
    assert not [x for x in limits if x["effect"] == "offset_wander"]


@pytest.mark.slow
def test_several_channels_that_only_drift_with_time_are_tested_as_one_term_and_named():
    # an outdoor warm-up: die temperature, ambient temperature and humidity all move
    # monotonically; tested against one another none of them could be tested at all
    run = _sim(161, drift_ut_per_s=(0.01, 0.0, -0.008))
    s = run.series
    frac = s.t_s / s.t_s[-1]
    rng = np.random.default_rng(161)
    chans = {
        "temp_c": 20.0 + 15.0 * frac,
        "ambient_c": 12.0 - 3.0 * frac + 0.05 * rng.standard_normal(len(frac)),
        "humidity_pct": 40.0 + 9.0 * frac + 0.1 * rng.standard_normal(len(frac)),
    }
    d = diagnose(Series(t_s=s.t_s, field_ut=s.field_ut, channels=chans))
    assert d.effects == ["time_drift"]
    f = _finding(d, "time_drift")
    assert set(f.evidence["confounded_with"].split(", ")) == set(chans)
    assert "equivalent_coef_ut_per_c" in f.evidence  # the temperature is among them


def test_a_channel_the_motion_cannot_test_is_named_under_limits():
    # a logged channel that follows the board's attitude (here the field's vertical share, as a
    # tilt or heading log would): an offset following it is a direction-dependent error, so it
    # cannot be tested; the user is told so instead of reading silence as "no effect"
    run = _sim(162)
    s = run.series
    h = s.field_ut - np.asarray(HARD)
    tilt = h[:, 2] / np.linalg.norm(h, axis=1)
    d = diagnose(Series(t_s=s.t_s, field_ut=s.field_ut, channels={"tilt_log": tilt}))
    assert "covariate:tilt_log" not in d.effects
    (lim,) = [x for x in d.to_dict()["limits"] if x["effect"] == "covariate:tilt_log"]
    assert lim["channel"] == "tilt_log" and "could not be tested" in lim["summary"]



def test_the_floor_by_direction_says_when_a_direction_is_never_pinned():
    from magcal.diagnose.channels import slow_term_floor, slow_term_floor_range
    from magcal.diagnose.limits import by_direction as _by_direction

    t = np.linspace(0.0, 1.0, 2000)
    temp = 20.0 + 10.0 * np.sin(2 * np.pi * t)
    turn = 2 * np.pi * 5 * t
    tilted = np.c_[np.cos(turn) * 0.8, np.sin(turn) * 0.8, np.full_like(t, 0.6)]  # level turns, dip 37°
    lo, hi = slow_term_floor_range(temp, tilted, 0.3, 4.0)
    assert lo < slow_term_floor(temp, 0.3, 4.0) < hi  # the vertical is pinned least
    flat = np.c_[np.cos(turn), np.sin(turn), np.zeros_like(t)]  # never any vertical component
    lo, hi = slow_term_floor_range(temp, flat, 0.3, 4.0)
    assert lo > 0 and hi is None
    assert _by_direction((lo, hi)).endswith("or more by its direction; along some, not at all)")
    assert json.dumps([lo, hi], allow_nan=False)  # no infinity in the JSON


@pytest.mark.slow
@pytest.mark.parametrize("seed,tilt", [(181, 20.0), (182, 30.0), (183, 45.0)])
def test_soft_iron_on_a_band_of_directions_is_found_and_modelled_not_called_wander(seed, tilt):
    # level ±20–45°, yaw free: over this band the degree-3/4 direction harmonics share much with
    # the soft-iron columns; as nuisances they used to take soft iron (0 of 5 directions
    # identifiable) and hand what they missed to an offset_wander in data with no wander
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    a = q @ np.diag([1.02, 0.99, 0.995]) @ q.T
    run = _sim(seed, motion=Motion("tilt", max_tilt_deg=tilt, period_s=20.0), distortion=tuple(map(tuple, a)))
    d = diagnose(run.series)
    assert d.effects == ["soft_iron"]
    assert not [x for x in d.to_dict()["limits"] if x["effect"] == "offset_wander"]
    assert d.final.rms_ut < 1.1 * d.simulated_rms_ut
    # where magcal fit's own calibration is returned and it is the sphere (seed 181: 3 of 5
    # directions identifiable), final and baseline are the same model, equal to rounding
    assert d.final_heldout_rms_ut <= d.baseline_heldout_rms_ut * (1 + 1e-12)


@pytest.mark.slow
def test_soft_iron_on_a_partial_sphere_is_not_hidden_by_the_noise_along_the_field():
    # a 1.7 % soft iron on a partial sphere (±42°) with 0.59 µT noise: when the soft-iron columns
    # were evaluated at the measurement, |d| carried the same radial noise as the residual, and
    # the block covariance of the test came out 4–5× too wide (F 4.3, p 0.015: not found)
    a = ((0.9883, -0.0086, 0.0015), (-0.0086, 0.999, 0.0022), (0.0015, 0.0022, 1.0127))
    sc = Scenario(physics=Physics(hard_iron_ut=(0.2, 22.51, 39.21), noise_ut=0.59, distortion=a),
                  motion=Motion("tilt", max_tilt_deg=42.16, period_s=26.62), seed=24684357)
    d = diagnose(sc.simulate(N, 50.0).series)
    assert d.effects == ["soft_iron"]
    assert d.final_heldout_rms_ut < d.baseline_heldout_rms_ut


@pytest.mark.parametrize("seed,hard,period,swing,coef,noise", [
    (16180339, (-1.06, 18.6, -32.71), 29.99, (34.46, 21.09), (-0.0633, 0.0173, 0.0591), 0.328),
    (16183339, (-21.2, -13.08, -33.45), 21.29, (15.66, 16.18), (-0.0155, -0.0544, -0.0392), 0.379),
])
def test_a_temperature_swing_that_is_mostly_a_curve_in_time_is_found(seed, hard, period, swing, coef, noise):
    # 1.3 cycles of temperature over the recording: 80–85 % of each direction of its term is a
    # quadratic in time (the slow wander nuisance), yet the whole term's F is 27–36. It used to be
    # refused as untestable (a fifth of the column required of every direction) or to fail the
    # wander gate (its trend, split with the quadratic wander, counted as unexplained wander)
    temp = Temperature(base_c=swing[0], swing_c=swing[1], period_s=N / 50.0 / 1.3)
    sc = Scenario(physics=Physics(hard_iron_ut=hard, noise_ut=noise, temp_coef_ut_per_c=coef),
                  motion=Motion("sphere", period_s=period), temperature=temp, seed=seed)
    d = diagnose(sc.simulate(N, 50.0).series)
    assert d.effects == ["temperature_drift"]
    k = np.array(_finding(d, "temperature_drift").params["coef_ut_per_unit"])
    assert np.linalg.norm(k - coef) < 0.3 * np.linalg.norm(coef)


def _band_with_temperature(seed, coef):
    """A level ±28° band of directions (yaw free) with 1.3 cycles of a 19 °C temperature swing."""
    temp = Temperature(base_c=34.4, swing_c=18.9, period_s=N / 50.0 / 1.3)
    sc = Scenario(physics=Physics(hard_iron_ut=(-16.6, 27.7, -32.1), noise_ut=0.45, temp_coef_ut_per_c=coef),
                  motion=Motion("tilt", max_tilt_deg=28.2, period_s=27.7), temperature=temp, seed=seed)
    return sc.simulate(N, 50.0)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [13, 20])
def test_a_temperature_on_a_band_of_directions_is_found_where_the_residual_shows_no_wander(seed):
    # on a band the offset the temperature moves lies nearly along the band's axis, where a slow
    # offset and a slow gain look alike, and the quadratic offset wander fitted as free columns
    # took most of the 1.3-cycle swing even without any wander: seed 13 was missed (F 2.9) and
    # seed 20 reported 25 % off. The nuisance is now fitted only where the residual shows a wander
    coef = (0.04, -0.07, -0.002)
    d = diagnose(_band_with_temperature(seed, coef).series)
    assert d.effects == ["temperature_drift"]
    k = np.array(_finding(d, "temperature_drift").params["coef_ut_per_unit"])
    assert np.linalg.norm(k - coef) < 0.2 * np.linalg.norm(coef)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [13, 15])
def test_a_temperature_channel_on_a_band_of_directions_is_not_credited_with_wander(seed):
    # the same band and swing with no temperature gain: silent without wander; with a slow
    # 0.8 µT wander the residual shows it, the quadratic is a nuisance again and the channel is
    # not credited with the wander
    run = _band_with_temperature(seed, (0.0, 0.0, 0.0))
    assert diagnose(run.series).effects == []
    assert "temperature_drift" not in diagnose(_wandering(run, seed, amp_ut=0.8)).effects


@pytest.mark.slow
@pytest.mark.parametrize("seed,tilt", [(302, 40.0), (301, 25.0)])
def test_soft_iron_beside_a_strong_current_is_neither_lost_nor_invented(seed, tilt):
    # an intermittent 3 A current moving the offset by 3.7 µT on a band or partial sphere: left
    # in the samples the soft-iron reference is fitted to, it dragged that fit along the
    # offset–gain valley (seed 302: a 100 µT radius and 36 % of soft iron) and the soft-iron
    # test, linearised there, missed a 1.5 % soft iron and found one where there was none
    def run(soft):
        off = 0.004 if soft else 0.0
        dist = ((1 + soft, off, 0.0), (off, 1 - soft / 2, 0.0), (0.0, 0.0, 1 - soft / 2))
        sc = Scenario(physics=Physics(hard_iron_ut=HARD, distortion=dist, current_coef_ut_per_a=(0.3, -0.8, 0.9), noise_ut=0.5),
                      motion=Motion("tilt", max_tilt_deg=tilt, period_s=20.0), current=Current(level_a=3.0, duty=0.4), seed=seed)
        return diagnose(sc.simulate(N, 50.0).series)

    with_soft = run(0.015)
    assert sorted(with_soft.effects) == ["current_interference", "soft_iron"]
    gains = _finding(with_soft, "soft_iron").params["principal_gains"]
    # 2.4 % between the extreme gains; estimated 2.2-2.6 % over seeds 400-411 at both tilts,
    # 2.1-2.7 % over 300-311 at 40° but 3.0 % on seed 302 (the failure this guards against
    # was 36 % of soft iron)
    assert 0.01 < max(gains) - min(gains) < 0.035
    assert run(0.0).effects == ["current_interference"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_small_soft_iron_beside_a_motor_current_of_twelve_microtesla_is_found(seed):
    # a current switching 11.7 µT of offset on and off, and 0.6 % of soft iron, on a full
    # sphere: linearised at no current term, the offset's second-order part,
    # (|δ|² − (u·δ)²)/2R while the current is on, is a quadratic form of the direction left in
    # the residual (the quiet sensor's soft-iron test measured 0.16-0.27 µT of it on these
    # seeds) and its misfit hid the true soft iron (p 0.015-0.11)
    dist = ((1.006, 0.002, 0.0), (0.002, 0.996, 0.001), (0.0, 0.001, 0.998))
    run = _sim(seed, distortion=dist, current_coef_ut_per_a=(3.0, -2.0, 1.5), current=Current(level_a=3.0, duty=0.4),
               noise_ut=0.4)
    d = diagnose(run.series)
    assert sorted(d.effects) == ["current_interference", "soft_iron"]
    quiet = _sim(seed, current_coef_ut_per_a=(3.0, -2.0, 1.5), current=Current(level_a=3.0, duty=0.4), noise_ut=0.05,
                 quantize=False)
    d = diagnose(quiet.series)
    assert d.effects == ["current_interference"]
    assert d.tests["candidates"]["soft_iron"]["effect_rms_ut"] < 0.01



def _band(seed, hard, noise, tilt, period, **phys):
    sc = Scenario(physics=Physics(hard_iron_ut=hard, noise_ut=noise, **phys),
                  motion=Motion("tilt", max_tilt_deg=tilt, period_s=period), seed=seed)
    return diagnose(sc.simulate(N, 50.0).series)


@pytest.mark.parametrize("seed,hard,dist,noise,tilt,period", [
    (7414000, (28.84, -18.15, 11.11), ((0.99605, -0.0013, 0.00411), (-0.0013, 0.99742, -0.00599), (0.00411, -0.00599, 1.00653)),
     0.328, 16.86, 23.69),
    (6655000, (-27.49, -29.83, -6.84), ((1.00501, 0.0022, 0.00301), (0.0022, 1.0091, 0.00222), (0.00301, 0.00222, 0.98589)),
     0.375, 23.57, 26.59),
])
def test_soft_iron_on_a_band_is_not_lost_beside_the_time_term_it_resembles(seed, hard, dist, noise, tilt, period):
    # a soft iron (gains 1 % and 1.5 % off) on a ±17° and a ±24° band swept with a period: soft
    # iron and an offset drifting in time look alike there, and tested beside each other neither
    # passed (soft iron p 0.08 and 0.06, time 0.02 and 0.8) though the pair together did; alone
    # soft iron explains more, is tested without the time columns and found
    d = _band(seed, hard, noise, tilt, period, distortion=dist)
    assert d.effects == ["soft_iron"]
    pair = _finding(d, "soft_iron").evidence["collinear_pair"]
    assert pair["chosen"] == "soft_iron" and pair["joint_p"] <= 0.01
    assert pair["p_alone"][0] < pair["p_alone"][1]
    gains = _finding(d, "soft_iron").params["principal_gains"]
    assert 0.01 < max(gains) - min(gains) < 0.04


@pytest.mark.slow
@pytest.mark.parametrize("seed,hard,dist,coef,noise,tilt,period,temp_c", [
    (918277645, (4.21, 10.59, -32.14), ((1.00556, -0.00381, -0.01392), (-0.00381, 0.99587, 0.00137), (-0.01392, 0.00137, 0.99856)),
     (0.0518, 0.0442, 0.0062), 0.422, 18.47, 27.87, (18.42, 21.25)),
    (6734000, (28.83, -27.73, 26.29), ((0.99598, -0.00355, 0.00281), (-0.00355, 1.01259, -0.00348), (0.00281, -0.00348, 0.99143)),
     (0.0018, 0.0786, 0.0234), 0.515, 19.19, 20.46, (15.49, 15.32)),
    (6724000, (-19.37, 17.24, -16.31), ((0.99495, 0.00404, 0.00234), (0.00404, 0.99537, -0.00995), (0.00234, -0.00995, 1.00968)),
     (0.0, 0.0, 0.0), 0.482, 23.24, 25.55, None),
])
def test_soft_iron_the_tests_leave_out_is_not_taken_for_wander_on_a_band(seed, hard, dist, coef, noise, tilt, period, temp_c):
    # white noise, no wander: on a band only some soft-iron directions are tested, and the soft
    # iron along the others, periodic in time as the band is swept, was left in the residual the
    # twin and the wander check judge. The twin learned it as 0.08 µT of wander at the sweep's
    # frequency (seed 918277645: both true terms lost to its inflation), or the Legendre check
    # called it a wander and the quadratic nuisance took the temperature or the soft iron
    # (6734000, 6724000). Judged with every candidate fitted, the residual is white
    swing = temp_c is not None
    temp = Temperature(base_c=temp_c[0], swing_c=temp_c[1], period_s=N / 50.0 / 1.3) if swing else Temperature()
    sc = Scenario(physics=Physics(hard_iron_ut=hard, noise_ut=noise, distortion=dist, temp_coef_ut_per_c=coef),
                  motion=Motion("tilt", max_tilt_deg=tilt, period_s=period), temperature=temp, seed=seed)
    d = diagnose(sc.simulate(N, 50.0).series)
    assert d.effects == (["soft_iron", "temperature_drift"] if swing else ["soft_iron"])
    assert d.tests["twin_null"]["draws"] == 0  # the twin is white, as the simulation is
    gains = _finding(d, "soft_iron").params["principal_gains"]
    assert 0.005 < max(gains) - min(gains) < 0.05  # 2.4–3.0 % injected, part of it along directions a band leaves open
    if swing:
        k = np.array(_finding(d, "temperature_drift").params["coef_ut_per_unit"])
        assert np.linalg.norm(k - coef) < 0.5 * np.linalg.norm(coef)


@pytest.mark.parametrize("seed,hard,drift,noise,tilt,period", [
    (6641000, (19.4, -0.75, -7.02), (0.00446, 0.00593, 0.00097), 0.442, 23.92, 27.63),
    (6431000, (36.99, 37.31, 36.63), (0.0045, -0.00338, 0.00114), 0.560, 22.45, 29.93),
])
def test_a_drift_on_a_band_is_not_taken_for_soft_iron(seed, hard, drift, noise, tilt, period):
    # the same likeness the other way: a 0.6–0.75 µT drift over the recording on a band, no soft
    # iron. Neither passed beside the other (time was missed); alone time explains more, and it
    # is the one found — soft iron is not credited with the drift
    d = _band(seed, hard, noise, tilt, period, drift_ut_per_s=drift)
    assert d.effects == ["time_drift"]
    f = _finding(d, "time_drift")
    assert f.evidence["collinear_pair"]["chosen"] == "time_drift"
    k = np.array(f.params["coef_ut_per_unit"])
    assert np.linalg.norm(k - drift) < 0.5 * np.linalg.norm(drift)
