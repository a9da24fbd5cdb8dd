"""Values and the physics simulator: forward model, determinism, coverage cells."""

import numpy as np
import pytest

from magcal.core.calibration import Calibration
from magcal.fit.cell_buffer import CellBuffer, WhenFull
from magcal.fit.coverage import cell_index, coverage
from magcal.sim.physics import Current, Physics, Scenario, Temperature, demo_scenario


def test_correct_inverts_distort_with_channel_terms():
    cal = Calibration([5, -3, 2], 48, soft_iron=[[1.02, 0.01, 0], [0.01, 0.97, 0.02], [0, 0.02, 1.0]],
                      coef_ut_per_unit={"temp_c": [0.1, 0, -0.05]}, reference={"temp_c": 25})
    h = np.random.default_rng(0).normal(size=(50, 3)) * 40
    ch = {"temp_c": np.linspace(15, 35, 50)}
    assert np.allclose(cal.correct(cal.distort(h, ch), ch), h)
    assert Calibration.from_dict(cal.to_dict()).close_to(cal, 0, 0)


def test_non_positive_soft_iron_is_refused():
    with pytest.raises(ValueError, match="positive definite"):
        Calibration([0, 0, 0], 50, soft_iron=np.diag([1, -1, 1]))


def test_physics_truth_inverts_the_simulation():
    sc = Scenario(physics=Physics(hard_iron_ut=(30, -10, 5), distortion=((1.05, 0.02, 0), (0.02, 0.95, 0), (0, 0, 1.0)),
                                  temp_coef_ut_per_c=(0.1, 0, 0), current_coef_ut_per_a=(0, 0.8, 0), noise_ut=0.0,
                                  quantize=False),
                  temperature=Temperature(swing_c=20), current=Current(level_a=2.0), seed=3)
    run = sc.simulate(2000, 50)
    h = run.truth.correct(run.series.field_ut, run.series.channels)
    assert np.allclose(np.linalg.norm(h, axis=1), 50.0, atol=1e-6)


def test_stream_sampling_equals_batch_simulation():
    sc = demo_scenario(4).with_physics(glitch_rate=0.01)
    run = sc.simulate(3000, 100)
    t = run.series.t_s
    raw, st2, _ = sc.measure(t[1234:1300], np.arange(1234, 1300))
    assert np.array_equal(raw, run.raw[1234:1300])


def test_same_seed_same_data_different_seed_different_data():
    a = demo_scenario(1).simulate(500).raw
    assert np.array_equal(a, demo_scenario(1).simulate(500).raw)
    assert not np.array_equal(a, demo_scenario(2).simulate(500).raw)


def test_overflow_sets_hofl_and_clamps():
    sc = Scenario(physics=Physics(hard_iron_ut=(1500.0, 900.0, 0.0)))
    run = sc.simulate(100)
    assert np.all(run.st2 & 0x08) and not run.series.valid.any()
    assert run.raw.max() <= 4095


def test_equal_area_cells_cover_uniform_directions_evenly():
    u = np.random.default_rng(1).normal(size=(200000, 3))
    counts = np.bincount(cell_index(u), minlength=128)
    assert counts.min() > 0.9 * counts.mean() and counts.max() < 1.1 * counts.mean()
    assert coverage(u[:5000]) == 1.0
    assert coverage(np.array([[0, 0, 1.0]])) == 1 / 128


def test_the_sessions_sample_buffer_is_bounded_and_balanced():
    s = CellBuffer(per_cell=4, when_full=WhenFull.REFUSE, centre_ut=np.zeros(3))
    for i in range(100):
        s.add(50.0, 0.0, 0.0, 0.02 * i)
    assert len(s) == 4
    u = np.random.default_rng(2).normal(size=(20000, 3))
    for i, (x, y, z) in enumerate((50 * u / np.linalg.norm(u, axis=1, keepdims=True)).tolist()):
        s.add(x, y, z, 2.0 + 0.02 * i)
    assert len(s) == s.capacity and s.coverage() == 1.0
    back = CellBuffer.from_state(s.to_state())
    assert np.array_equal(back.field_ut, s.field_ut)
