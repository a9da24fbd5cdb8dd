"""The sensor's noise law (``magcal.sim.noise_law``): heavy-tailed white noise drawn at the
noise's RMS, stored in the sensor model, learned by the twin from a recording's tails."""

import dataclasses

import numpy as np
import pytest

from magcal.core.calibration import Calibration
from magcal.diagnose import twin
from magcal.diagnose.twin import stats as ts
from magcal.fit import fit_calibration as fit
from magcal.sim.model import SensorModel
from magcal.sim.noise_law import NoiseLaw
from magcal.sim.physics import Motion, Physics, Scenario
from magcal.sim.wander import WanderComponent


def _sensor(level_sd: float) -> SensorModel:
    cal = Calibration(offset_ut=[12.0, -20.0, 30.0], field_ut=50.0,
                      soft_iron=[[1.03, 0.01, 0.0], [0.01, 0.97, 0.0], [0.0, 0.0, 1.0]])
    return SensorModel(calibration=cal, noise_ut=(0.3, 0.3, 0.35), wander=(WanderComponent(0.05, 5.0),),
                       noise_law=NoiseLaw(level_sd))


def _recording(model: SensorModel, seed: int = 7, n: int = 3000):
    return Scenario(physics=Physics(), motion=Motion("sphere", period_s=15.0), seed=seed, model=model).simulate(n).series


def test_a_heavy_law_keeps_the_noise_rms_and_gaussian_noise_is_drawn_as_before():
    t = np.arange(40000) / 50.0
    gauss, heavy = _sensor(0.0), _sensor(0.5)
    a, b = gauss.draws(t, 3).noise, heavy.draws(t, 3).noise
    assert np.array_equal(a, dataclasses.replace(gauss, noise_law=NoiseLaw()).draws(t, 3).noise)
    assert abs(np.mean(b**2) - 1.0) < 0.05  # σ is still the noise's RMS
    kurt = np.mean(b**4) / np.mean(b**2) ** 2
    assert abs(np.mean(a**4) - 3.0) < 0.15 and 0.8 < kurt / heavy.noise_law.kurtosis < 1.2, kurt
    assert ts.tail_ratio(b[:, 0]) > 1.4 * ts.tail_ratio(a[:, 0])


def test_the_law_is_stored_in_the_model_and_a_bad_one_is_named():
    model = _sensor(0.4)
    back = SensorModel.from_dict(model.to_dict())
    assert back.noise_law == NoiseLaw(0.4) and "noise_law" in back.effects()
    old = {k: v for k, v in model.to_dict().items() if k != "noise_law"} | {"schema": "magcal.sensor-model/8"}
    assert SensorModel.from_dict(old).noise_law.gaussian
    assert model.without("noise_law").noise_law.gaussian
    with pytest.raises(ValueError, match="level_sd"):
        SensorModel.from_dict(model.to_dict() | {"noise_law": {"level_sd": -0.1}})
    with pytest.raises(ValueError, match="level_sd"):
        SensorModel.from_dict(model.to_dict() | {"noise_law": {"level_sd": "wide"}})


def test_a_board_simulated_with_a_heavy_law_reads_its_noise_at_each_reads_level():
    heavy = _recording(_sensor(0.6), n=2000).field_ut
    gauss = _recording(_sensor(0.0), n=2000).field_ut
    d_heavy, d_gauss = (np.diff(m, 2, axis=0).ravel() for m in (heavy, gauss))
    assert ts.tail_ratio(d_heavy) > 1.3 * ts.tail_ratio(d_gauss)


@pytest.mark.parametrize("level_sd", [0.0, 0.5])
def test_the_twin_learns_the_noise_law_and_its_twins_hold_the_recordings_tails(level_sd):
    """A recording with Gaussian noise learns Gaussian noise; one whose noise level varies from
    read to read learns that law, and its twins' tail ratio then holds the recording's, which
    Gaussian twins do not."""
    rec = _recording(_sensor(level_sd))
    model = twin.learn(rec, fit(rec.field_ut, model="ellipsoid").calibration)
    if level_sd == 0.0:
        assert model.noise_law.level_sd < 0.1, model.noise_law
        return
    assert abs(model.noise_law.level_sd - level_sd) < 0.15, model.noise_law
    for m, inside in ((model, True), (model.without("noise_law"), False)):
        assert {b.name: b for b in twin.compare(m, rec, 20, 5).bands}["tail_ratio"].inside == inside


def test_a_heavy_wander_keeps_its_variance_and_makes_larger_excursions():
    t = np.arange(20000) / 50.0
    comps = (WanderComponent(0.5, 0.5), WanderComponent(0.3, 2.0, frame="field"))
    gauss = dataclasses.replace(_sensor(0.0), wander=comps)
    heavy = dataclasses.replace(gauss, noise_law=NoiseLaw(wander_h=0.3))
    a, b = gauss.draws(t, 5), heavy.draws(t, 5)
    for x, y in ((a.wander_ut, b.wander_ut), (a.field_wander_ut, b.field_wander_ut)):
        assert abs(np.var(y) / np.var(x) - 1.0) < 0.2
        assert np.array_equal(np.sign(x), np.sign(y))  # the same path, its excursions stretched
        assert ts.tail_ratio(y.ravel()) > 1.5 * ts.tail_ratio(x.ravel())
