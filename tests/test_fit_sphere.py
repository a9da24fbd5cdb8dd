"""ML sphere: unbiased where the normal equations are not, honest about its uncertainty."""

import numpy as np
import pytest

from magcal.fit import SphereAccumulator, fit_sphere
from magcal.fit.uncertainty import crlb_offset, summarise


def cap_points(n, centre, radius, half_angle_deg, noise, seed):
    """Directions uniform on a cap of the given half-angle around +z (a ±θ tilt recording)."""
    rng = np.random.default_rng(seed)
    cos_min = np.cos(np.deg2rad(half_angle_deg))
    z = rng.uniform(cos_min, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    u = np.column_stack([s * np.cos(phi), s * np.sin(phi), z])
    return np.asarray(centre) + radius * u + noise * rng.normal(size=(n, 3))


def test_ml_sphere_is_unbiased_on_a_cap_where_the_normal_equations_are_not():
    centre = np.array([10.0, -20.0, 5.0])
    err_ml, err_alg = [], []
    for seed in range(30):
        m = cap_points(600, centre, 50.0, 30.0, 0.5, seed)
        acc = SphereAccumulator()
        acc.add_batch(m)
        alg = acc.solve(max_condition=np.inf)
        ml = fit_sphere(m)
        err_alg.append(alg.offset_ut - centre)
        err_ml.append(ml.offset_ut - centre)
    bias_alg = np.mean(err_alg, axis=0)
    bias_ml = np.mean(err_ml, axis=0)
    sem_ml = np.std(err_ml, axis=0) / np.sqrt(len(err_ml))
    assert abs(bias_alg[2]) > 1.0  # the algebraic weighting pulls the centre along the cap axis
    assert np.all(np.abs(bias_ml) < 4 * sem_ml + 0.05)


def test_reported_uncertainty_matches_the_scatter_over_repeats():
    centre = np.array([-30.0, 15.0, 40.0])
    est, sig = [], []
    for seed in range(40):
        m = cap_points(800, centre, 48.0, 60.0, 0.4, 100 + seed)
        f = fit_sphere(m)
        est.append(f.offset_ut)
        sig.append(summarise(f)["offset_ut"])
    ratio = np.std(est, axis=0) / np.mean(sig, axis=0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


def test_crlb_equals_the_radial_jacobian_formula():
    m = cap_points(300, (0, 0, 0), 50.0, 45.0, 0.0, 3)
    u = m / np.linalg.norm(m, axis=1, keepdims=True)
    J = np.column_stack([u, np.ones(len(u))])
    expected = 0.4**2 * np.linalg.inv(J.T @ J)[:3, :3]
    assert np.allclose(crlb_offset(m, (0, 0, 0), 50.0, 0.4), expected, rtol=1e-9, atol=0)


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (900.0, -900.0, 600.0)])
def test_ml_sphere_recovers_exact_spheres_anywhere(centre):
    m = cap_points(200, centre, 45.0, 180.0, 0.0, 1)
    f = fit_sphere(m)
    assert np.allclose(f.offset_ut, centre, atol=1e-6)
    assert abs(f.field_ut - 45.0) < 1e-6
    assert f.rms_ut < 1e-6


def test_non_finite_input_is_a_failure_value():
    m = cap_points(50, (0, 0, 0), 45.0, 180.0, 0.1, 1)
    m[3, 1] = np.nan
    f = fit_sphere(m)
    assert not f and f.reason == "non_finite"
