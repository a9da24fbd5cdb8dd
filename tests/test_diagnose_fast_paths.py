"""The fast paths of the fit and of the twin's draws give what the straightforward forms give:
the geometric Jacobian (built a parameter at a time) against the per-column products and
against finite differences, the row norms against numpy's, the Lagrange reading of a draw
against the polynomial itself, the sphere's residual without its matrix exponential against
the one with it, diagnosis's model Jacobian against finite differences, a twin's draws on
times in order against the same draws on the times shuffled, the kept checks of a stream's
times against fresh ones; and a whole diagnosis — the fit's Levenberg–Marquardt steps, its
Grubbs critical values, the twin's draws and the Whittle fit's non-negative solves — made with
the straightforward forms put back finds the same effects with the same coefficients, on a
simulated recording and on a real excerpt whose bursty stamps make the twin read its draws
between grid points."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.diagnose import diagnose
from magcal.diagnose import model as diagnose_model
from magcal.fit import fit_calibration, geometric, outliers
from magcal.sim import nnls as nnls_module
from magcal.sim import wander
from magcal.sim.model import SensorModel
from magcal.sim.physics import Motion, Physics, Scenario, Temperature

DATA = Path(__file__).parent / "data"


def _reference_jacobian(theta, m, kind, forward=None):
    """∂e/∂θ column by column, for e = g/s with g = |h| − r, h = W d, u = h/|h|, s = |W u|:
    ∂e = ∂g/s − g ∂s/s², with ∂g = uᵀ ∂h and ∂s = (W u/s)ᵀ (∂W u + W (I − u uᵀ) ∂h/|h|)."""
    theta = np.asarray(theta, dtype=np.float64)
    W, dWs = geometric.expm_derivatives(kind, theta[4:])
    d = m - theta[:3]
    h = d @ W.T
    nh = np.linalg.norm(h, axis=1)
    u = h / nh[:, None]
    v = u @ W.T
    s = np.linalg.norm(v, axis=1)
    g = nh - theta[3]
    w = v / s[:, None]

    def across(x):  # (I − u uᵀ) x per row
        return x - u * np.einsum("ij,ij->i", u, x)[:, None]

    def de(dh, dWu):  # dh, dWu (n, 3): ∂h and ∂W u along one parameter
        dg = np.einsum("ij,ij->i", u, dh)
        ds = np.einsum("ij,ij->i", w, dWu + across(dh) @ W.T / nh[:, None])
        return (dg / s - g * ds / s**2)[:, None]

    zero = np.zeros_like(d)
    cols = [de(np.tile(-W[:, k], (len(m), 1)), zero) for k in range(3)]
    cols.append((-1.0 / s)[:, None])
    cols += [de(d @ dW.T, u @ dW.T) for dW in dWs]
    return np.hstack(cols)


def _reference_lagrange(grid, pos):
    """The Lagrange polynomial through the 8 grid points around each position, weights by the
    barycentric formula on an (n, taps) array."""
    taps = wander.TAPS
    denominator = np.array([np.prod([xi - xj for xj in taps if xj != xi]) for xi in taps], dtype=np.float64)
    below = np.floor(pos)
    d = (pos - below)[:, None] - taps
    at = d == 0
    d[at] = 1.0
    w = np.prod(d, axis=1, keepdims=True) / d / denominator
    w[at.any(axis=1)] = at[at.any(axis=1)]
    idx = (below.astype(np.int64)[:, None] + taps) % len(grid)
    return np.einsum("nt,ntk->nk", w, grid[idx])


def _reference_forward(theta, mt, kind):
    """``geometric._forward`` with W = expm(S) made for every kind, the sphere's too, and the
    raw-space scale |W u| computed for it too."""
    eig = geometric.expm_sym(geometric.shape_matrix(kind, theta[4:]))
    d = mt - theta[:3, None]
    h = eig[0] @ d
    nh = np.sqrt((h[0] * h[0] + h[1] * h[1]) + h[2] * h[2])
    return d, h, nh, eig, np.linalg.norm(eig[0] @ (h / nh), axis=0)


def _cold_nnls(a, b, maxiter=None, start=None):
    """Every non-negative solve from the empty active set."""
    return nnls_module.nnls(a, b, maxiter)


def _real_excerpt():
    return load_series(DATA / "hmc5883l_sunsided_full_sphere_every3rd.csv")


def _simulated():
    sc = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.4, temp_coef_ut_per_c=(0.04, -0.03, 0.02),
                                  distortion=((1.012, 0.004, 0.0), (0.004, 0.991, 0.003), (0.0, 0.003, 1.0))),
                  motion=Motion("sphere", period_s=20.0), temperature=Temperature(base_c=20.0, swing_c=20.0, period_s=60.0),
                  seed=20261123)
    return sc.simulate(5000, 50.0).series


@pytest.mark.parametrize("kind", ["sphere", "diagonal", "full"])
def test_the_jacobian_is_the_column_by_column_one_and_the_finite_difference(kind):
    m = _real_excerpt().field_ut
    theta = np.concatenate([[3.0, -12.0, 1.5, 50.0], [0.02, -0.015, 0.01, -0.004, 0.006][: geometric.N_SHAPE[kind]]])
    J = geometric.jacobian(theta, m, kind)
    np.testing.assert_allclose(J, _reference_jacobian(theta, m, kind), rtol=0, atol=1e-12 * np.abs(J).max())
    step = 1e-6
    for k in range(len(theta)):
        dt = np.zeros(len(theta))
        dt[k] = step
        fd = (geometric.residual(theta + dt, m, kind) - geometric.residual(theta - dt, m, kind)) / (2 * step)
        np.testing.assert_allclose(J[:, k], fd, rtol=0, atol=1e-6 * max(1.0, np.abs(J[:, k]).max()))


def test_the_row_norm_is_numpys():
    v = np.random.default_rng(5).standard_normal((4001, 3)) * [40.0, 3.0, 0.2]
    np.testing.assert_allclose(geometric.row_norm(v), np.linalg.norm(v, axis=1), rtol=4e-16, atol=0)


def test_a_reading_between_grid_points_is_the_polynomial_through_its_taps():
    rng = np.random.default_rng(11)
    size = 64
    pos = np.concatenate([rng.uniform(0, size, 500), np.arange(0.0, size, 1.0), [size - 0.5, 0.25]])
    grid = rng.standard_normal((size, 3))
    got = wander._lagrange(grid, pos)
    np.testing.assert_allclose(got, _reference_lagrange(grid, pos), rtol=0, atol=1e-13)
    on_grid = pos == np.floor(pos)
    np.testing.assert_array_equal(got[on_grid], grid[pos[on_grid].astype(int) % size])
    # a polynomial of degree 7 is read exactly away from the wrap
    x = np.arange(size, dtype=np.float64)
    poly = np.polynomial.Polynomial([0.3, -1.0, 0.5, 0.2, -0.05, 0.01, -0.001, 1e-5])
    inner = (pos > 4) & (pos < size - 5)
    read = wander._lagrange((poly(x / 8.0))[:, None], pos[inner].copy())  # the kept reading is not reused
    np.testing.assert_allclose(read[:, 0], poly(pos[inner] / 8.0), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(wander._lagrange(grid, pos.copy()), got)  # read again: the same


def test_the_spheres_residual_and_jacobian_without_the_exponential_are_those_with_it():
    m = _real_excerpt().field_ut
    theta = np.array([3.0, -12.0, 1.5, 50.0])
    fast = geometric._forward(theta, geometric._columns(m), "sphere")
    slow = _reference_forward(theta, geometric._columns(m), "sphere")
    for a, b in zip(fast[:3], slow[:3]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(geometric.jacobian(theta, m, "sphere", fast), geometric.jacobian(theta, m, "sphere", slow))


def test_diagnosis_model_jacobian_is_the_finite_difference():
    s = _simulated()
    m, x = s.field_ut, s.channels["temp_c"] - 20.0
    spec = diagnose_model.Spec(soft_iron=True, channels=("temp_c",))
    p = np.concatenate([[21.0, -33.0, 8.0], [0.01, -0.004, 0.003, 0.0, 0.002], [49.0], [0.04, -0.03, 0.02]])
    e, J = diagnose_model.residual_jacobian(p, spec, m, [x])
    assert J.shape == (len(m), spec.n_params) and J.flags["C_CONTIGUOUS"]
    step = 1e-6
    for k in range(len(p)):
        dp = np.zeros(len(p))
        dp[k] = step
        fd = (diagnose_model.residual_jacobian(p + dp, spec, m, [x], False)[0]
              - diagnose_model.residual_jacobian(p - dp, spec, m, [x], False)[0]) / (2 * step)
        np.testing.assert_allclose(J[:, k], fd, rtol=0, atol=1e-6 * max(1.0, np.abs(J[:, k]).max()))


def test_a_twins_draws_on_times_in_order_are_its_draws_on_the_times_shuffled():
    t = np.sort(np.random.default_rng(2).uniform(0.0, 30.0, 400))
    model = SensorModel(calibration=_simulated_calibration(), wander=(wander.WanderComponent(0.3, band_hz=(0.05, 2.0)),
                                                                      wander.WanderComponent(0.2, tau_s=3.0)))
    in_order = model.draws(t, 7)
    shuffle = np.random.default_rng(3).permutation(len(t))
    shuffled = model.draws(t[shuffle], 7)
    np.testing.assert_array_equal(shuffled.wander_ut, in_order.wander_ut[shuffle])
    np.testing.assert_array_equal(shuffled.field_wander_ut, in_order.field_wander_ut[shuffle])


def test_the_kept_checks_of_a_streams_times_do_not_carry_over_to_other_times():
    comps = (wander.WanderComponent(0.3, band_hz=(0.5, 4.0)),)
    uniform = np.arange(600) * 0.02
    jittered = uniform + np.random.default_rng(5).uniform(-0.004, 0.004, 600)
    for first, second in ((uniform, jittered), (jittered, uniform)):
        wander.draw_path(comps, np.random.default_rng(1), first)  # its checks and reading are kept
        again = wander.draw_path(comps, np.random.default_rng(1), second)
        wander._LAST_UNIFORM[0] = wander._LAST_READING[0] = None
        fresh = wander.draw_path(comps, np.random.default_rng(1), second)
        np.testing.assert_array_equal(again[0], fresh[0])
    assert wander._fast_len(7501) == 7680 and wander._fast_len(16) == 16


def _simulated_calibration():
    from magcal.core.calibration import Calibration

    return Calibration(offset_ut=(21.0, -33.0, 8.0), field_ut=49.0)


def _uncached_block(start, stop, alpha):
    return np.atleast_1d(outliers.grubbs_critical(np.arange(start, stop, -1), alpha))


@pytest.fixture
def straightforward(monkeypatch):
    """The fit's and the draws' straightforward forms put back."""
    readings = []

    def lagrange(grid, pos):
        readings.append(len(pos))
        return _reference_lagrange(grid, pos)

    def put_back():
        monkeypatch.setattr(geometric, "jacobian", _reference_jacobian)
        monkeypatch.setattr(geometric, "row_norm", lambda v: np.linalg.norm(v, axis=1))
        monkeypatch.setattr(outliers, "_critical_block", _uncached_block)
        monkeypatch.setattr(wander, "_lagrange", lagrange)
        monkeypatch.setattr(geometric, "_forward", _reference_forward)
        monkeypatch.setattr(wander, "nnls", _cold_nnls)
        return readings
    return put_back


def _same(a, b, path=""):
    """Numbers to 1e-6 relative (the fit's stopping tolerance leaves the last digits free),
    text the same word for word with its numbers set aside, everything else equal."""
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            _same(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{path}[{i}]")
    elif isinstance(a, str):
        number = r"[-+]?\d[\d.]*(e[-+]?\d+)?"
        assert re.sub(number, "#", a) == re.sub(number, "#", b), path
    elif isinstance(a, float) and isinstance(b, float):
        assert (np.isnan(a) and np.isnan(b)) or abs(a - b) <= 1e-6 * max(abs(a), abs(b)) + 1e-12, (path, a, b)
    else:
        assert a == b, path


@pytest.mark.slow
@pytest.mark.parametrize("recording", [_simulated, _real_excerpt], ids=["simulated", "hmc5883l_excerpt"])
def test_a_diagnosis_is_the_one_the_straightforward_forms_make(recording, straightforward):
    series = recording()
    fast = diagnose(series)
    fit_fast = fit_calibration(series, model="auto")
    readings = straightforward()
    slow = diagnose(series)
    fit_slow = fit_calibration(series, model="auto")
    assert fast.effects == slow.effects and fast.calibration_from == slow.calibration_from
    _same(fast.to_dict(), slow.to_dict())
    assert fit_fast.model == fit_slow.model
    np.testing.assert_array_equal(fit_fast.outliers, fit_slow.outliers)
    for name in ("offset_ut", "soft_iron"):
        np.testing.assert_allclose(getattr(fit_fast.calibration, name), getattr(fit_slow.calibration, name),
                                   rtol=0, atol=1e-7)
    if recording is _real_excerpt:
        assert readings  # the twin was drawn between grid points: its readings were compared too
