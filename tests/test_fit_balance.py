"""The direction balance under "auto": given where the motion saw enough of the sphere, not
where the shape is extrapolated over most of it."""

import numpy as np

from magcal.fit import fit_calibration

BALANCED = "samples weighted so each direction cell counts equally"


def _cap_with_rest(seed: int, z_min: float, n: int = 4000, rest: int = 1500) -> np.ndarray:
    """A wandering hand turn whose field directions stay at z ≥ ``z_min`` (a cap), then a long
    rest in the last pose, through a full soft iron and a hard iron."""
    rng = np.random.default_rng(seed)
    v, path = np.array([0.0, 0.0, 1.0]), []
    while len(path) < n:
        w = v + 0.08 * rng.normal(size=3)
        w /= np.linalg.norm(w)
        if w[2] >= z_min:
            v = w
        path.append(v.copy())
    u = np.array(path)
    u = np.concatenate([u, u[-1] + 0.005 * rng.normal(size=(rest, 3))])
    u /= np.linalg.norm(u, axis=1)[:, None]
    soft = np.eye(3) + np.array([[0.04, 0.02, -0.01], [0.02, -0.03, 0.015], [-0.01, 0.015, 0.01]])
    return (50.0 * u) @ soft.T + np.array([12.0, -25.0, 8.0]) + 0.1 * rng.normal(size=u.shape)


def test_a_cap_under_half_the_sphere_is_fitted_unweighted_and_says_why():
    m = _cap_with_rest(0, z_min=0.3)  # 38 % of the cells
    auto, plain = fit_calibration(m, model="auto"), fit_calibration(m, model="ellipsoid", balance="none")
    assert auto.model == "ellipsoid" and BALANCED not in auto.reason
    assert "no direction balance: 38 % of directions seen" in auto.reason
    assert np.allclose(auto.calibration.offset_ut, plain.calibration.offset_ut, atol=1e-9)
    assert np.allclose(auto.calibration.soft_iron, plain.calibration.soft_iron, atol=1e-12)


def test_over_half_the_sphere_the_long_rest_is_balanced():
    m = _cap_with_rest(0, z_min=-0.2)  # 61 % of the cells
    auto = fit_calibration(m, model="auto")
    assert auto.model == "ellipsoid" and BALANCED in auto.reason
    plain = fit_calibration(m, model="ellipsoid", balance="none")
    assert not np.allclose(auto.calibration.offset_ut, plain.calibration.offset_ut, atol=1e-6)
