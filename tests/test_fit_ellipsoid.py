"""Ellipsoid: the note's correction mapping against the forward model, PD always, thin coverage."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.core.calibration import Calibration
from magcal.fit import FitFailure, algebraic_quadric, fit_calibration, fit_ellipsoid, quadric_to_correction
from magcal.fit.ellipsoid import correct_with_note
from magcal.sim.physics import Motion, Physics, Scenario

DISTORTION = ((1.08, 0.03, -0.02), (0.03, 0.94, 0.025), (-0.02, 0.025, 1.01))


def unit_sphere(n, seed):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def truth_cal(offset=(20.0, -30.0, 5.0), field=48.0):
    return Calibration(offset_ut=offset, field_ut=field, soft_iron=np.linalg.inv(np.array(DISTORTION)))


def test_note_mapping_inverts_the_forward_model_exactly():
    cal = truth_cal()
    h = 48.0 * unit_sphere(400, 0)
    m = cal.distort(h)
    q = algebraic_quadric(m)
    centre, W1 = quadric_to_correction(*q)
    assert np.allclose(centre, cal.offset_ut, atol=1e-8)
    # W1 maps onto the unit sphere: W1 · field = the true correction matrix
    assert np.allclose(W1 * 48.0, cal.soft_iron, atol=1e-9)
    # the note's formula, applied literally, is the same map
    X = correct_with_note(m, *q)
    assert np.allclose(X, (m - centre) @ W1.T, atol=1e-12)
    assert np.allclose(np.linalg.norm(X, axis=1), 1.0, atol=1e-9)


def test_negated_quadric_gives_the_same_correction():
    m = truth_cal().distort(48.0 * unit_sphere(200, 1))
    A, B, c = algebraic_quadric(m)
    c1, W1 = quadric_to_correction(A, B, c)
    c2, W2 = quadric_to_correction(-A, -B, -c)
    assert np.allclose(c1, c2) and np.allclose(W1, W2)


@pytest.mark.parametrize("kind", ["full", "diagonal"])
def test_ml_ellipsoid_recovers_soft_iron_from_noisy_full_coverage(kind):
    D = np.array(DISTORTION) if kind == "full" else np.diag(np.diag(DISTORTION))
    cal = Calibration(offset_ut=(20.0, -30.0, 5.0), field_ut=48.0, soft_iron=np.linalg.inv(D))
    rng = np.random.default_rng(2)
    m = cal.distort(48.0 * unit_sphere(2000, 2)) + 0.3 * rng.normal(size=(2000, 3))
    f = fit_ellipsoid(m, kind=kind)
    assert f, f
    W = f.soft_iron
    assert abs(np.linalg.det(W) - 1.0) < 1e-9
    # compare shapes at equal scale (magnitudes cannot fix the overall scale)
    Wt = cal.soft_iron / np.cbrt(np.linalg.det(cal.soft_iron))
    assert np.allclose(W, Wt, atol=2e-3)
    assert np.allclose(f.offset_ut, cal.offset_ut, atol=0.1)
    # the full calibration undoes the distortion: corrected magnitudes are constant
    h = (m - f.offset_ut) @ W.T
    assert np.std(np.linalg.norm(h, axis=1)) < 0.35


def test_hyperboloid_start_on_poor_coverage_is_detected_and_the_fit_stays_positive_definite():
    run = Scenario(physics=Physics(hard_iron_ut=(30, -20, 10)), motion=Motion("tilt", max_tilt_deg=10), seed=3).simulate(1500)
    m = run.series.field_ut
    plain = algebraic_quadric(m, ellipsoid_specific=False)
    verdict = quadric_to_correction(*plain)
    assert isinstance(verdict, FitFailure) and verdict.reason == "not_positive_definite"
    assert "hyperboloid" in verdict.message
    result = fit_calibration(run.series, model="ellipsoid")
    assert result
    assert np.all(np.linalg.eigvalsh(result.calibration.soft_iron) > 0)
    assert result.model == "sphere" and "coverage" in result.reason  # the coverage cannot determine the gains
    assert np.allclose(result.calibration.offset_ut, (30, -20, 10), atol=2.0)


@settings(max_examples=25, deadline=None)
@pytest.mark.slow
@given(
    seed=st.integers(0, 10_000),
    tilt=st.sampled_from([5.0, 20.0, 45.0, 90.0]),
    n=st.integers(15, 400),
    kind=st.sampled_from(["full", "diagonal"]),
    noise=st.floats(0.05, 3.0),
)
def test_an_ellipsoid_fit_never_returns_a_non_positive_definite_matrix(seed, tilt, n, kind, noise):
    rng = np.random.default_rng(seed)
    cos_min = np.cos(np.deg2rad(tilt))
    z = rng.uniform(cos_min, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    h = 50.0 * np.column_stack([s * np.cos(phi), s * np.sin(phi), z])
    m = truth_cal().distort(h) + noise * rng.normal(size=(n, 3))
    f = fit_ellipsoid(m, kind=kind)
    if f:
        assert np.all(np.linalg.eigvalsh(f.soft_iron) > 0)
        assert f.field_ut > 0
    else:
        assert isinstance(f, FitFailure) and f.reason and f.message
    r = fit_calibration(m, model="ellipsoid")
    if r:
        assert np.all(np.linalg.eigvalsh(r.calibration.soft_iron) > 0)


def test_model_choice_follows_what_the_coverage_supports():
    phys = Physics(hard_iron_ut=(23.5, -41.2, 12.8), distortion=DISTORTION)
    full = Scenario(physics=phys, motion=Motion("sphere"), seed=4).simulate(1500)
    r = fit_calibration(full.series, model="auto")
    assert r.model == "ellipsoid"
    tilt = Scenario(physics=phys, motion=Motion("tilt", max_tilt_deg=30), seed=4).simulate(1500)
    r = fit_calibration(tilt.series, model="ellipsoid")
    assert r.model == "sphere" and "the coverage determines its gains only to" in r.reason
    yaw = Scenario(physics=phys, motion=Motion("yaw"), seed=4).simulate(1500)
    r = fit_calibration(yaw.series, model="auto")
    assert not r and r.reason == "ill_conditioned"


def test_auto_keeps_the_sphere_when_there_is_no_soft_iron():
    run = Scenario(physics=Physics(hard_iron_ut=(10, 20, 30)), motion=Motion("sphere"), seed=1).simulate(1500)
    r = fit_calibration(run.series, model="auto")
    assert r.model == "sphere" and "held-out" in r.reason
    assert np.array_equal(r.calibration.soft_iron, np.eye(3))
