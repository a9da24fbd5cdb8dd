"""bench/model_choice.py on a recording where ``fit --model auto`` refuses every training part
(a take that is still until its last tenth, like a rocket on its rail): the bench reports the
refused cells and its summary instead of failing on an empty set of ratios."""

import importlib.util
import os

import numpy as np

BENCH = os.path.join(os.path.dirname(__file__), "..", "bench", "model_choice.py")


def _bench():
    spec = importlib.util.spec_from_file_location("model_choice_bench", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_recording_refused_in_every_cell_is_summarised(capsys):
    rng = np.random.default_rng(7)
    still = np.array([20.0, -5.0, 40.0]) + rng.normal(0.0, 0.05, (400, 3))
    ratios = _bench().run({"still": still}, (0.3, 0.5, 0.7))
    out = capsys.readouterr().out
    assert len(ratios) == 3 and not np.any(np.isfinite(ratios))
    assert out.count("| still |") == 3 and "refused" in out
    assert "3 cells: none scored, auto refused in 3" in out
