"""A held-out block is judged by models refitted on the other blocks alone: what the whole
recording (the held-out block included) said of a model must not reach its score there."""

from types import SimpleNamespace

import numpy as np

from magcal.diagnose.heldout import compare_heldout
from magcal.diagnose.model import Spec, fit_model


def _cap_then_turn(rng) -> np.ndarray:
    """800 readings within a few degrees of +x (a cap whose curvature is below the noise: the
    sphere open), then 200 over every direction, around an offset of (10, −5, 20) µT on a 50 µT
    field with 1 µT noise."""
    def dirs(n, cap):
        v = rng.normal(size=(n, 3))
        if cap:
            v[:, 0] = np.abs(v[:, 0]) + 15.0
        return v / np.linalg.norm(v, axis=1, keepdims=True)
    u = np.vstack([dirs(800, True), dirs(200, False)])
    return np.array([10.0, -5.0, 20.0]) + 50.0 * u + rng.normal(0.0, 1.0, (1000, 3))


def test_a_blocks_score_does_not_depend_on_the_whole_recordings_values():
    rng = np.random.default_rng(7)
    m = _cap_then_turn(rng)
    a = SimpleNamespace(m=m, chans={}, keep=np.ones(len(m), bool))
    whole = fit_model(m, {}, Spec())
    elsewhere = fit_model(m + np.array([0.0, 0.0, 30.0]), {}, Spec())  # the same model, other values
    assert abs(elsewhere.offset_ut[2] - whole.offset_ut[2]) > 25.0
    folds = [slice(k, k + 200) for k in range(0, 1000, 200)]
    held = compare_heldout(a, [whole, elsewhere], folds)
    assert len(held.per_block) >= 4
    for by_whole, by_elsewhere in held.per_block:
        assert by_whole == by_elsewhere
