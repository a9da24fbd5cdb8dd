"""The sensor twin: learn a SensorModel from a recording, draw twins of it, compare, name.

One module per job:

- ``learning`` — ``learn`` turns a calibration (the deterministic part diagnosis or fit found)
  and the recording's residuals into a :class:`~magcal.sim.model.SensorModel`; with it
  ``spikes`` (glitches in a recording), ``glitch_rate`` (the glitch process twins confirm),
  ``events`` (intermittent disturbances), ``noise`` (correlated noise, repeated reads) and
  ``takes`` (a recording made of placements);
- ``draw`` — twins of a recording along its own directions, refitted as it is
  (``residual``: the refit and the residual it leaves);
- ``comparison`` — ``compare``, the parametric bootstrap: the statistics of ``stats`` on the
  recording against the band of its twins; ``names`` locates and names each mismatch;
- ``steps`` — ``compare_steps``: the comparison for the baseline (hard iron + white noise)
  and for the model with each effect added in turn, ending at the learned model;
- ``text`` — the steps as text lines for ``magcal diagnose --twin``.
"""

from .comparison import BAND, DRAWS, ORIENTATION_WORDS, Band, StepComparison, compare
from .draw import replayed, twin_directions, twin_draw, twin_draws, twin_readings
from .events import EVENT_EDGE, EVENT_MIN, EVENT_Z, MAX_EVENTS, disturbances, event_pairs
from .glitch_rate import along_the_field, glitch_process
from .learning import CV_GAIN, TAKE_SEEDS, learn, placements
from .names import Mismatch, direction_words, locate, mismatches
from .noise import NOISE_LAG1_MAX, NOISE_LAG1_Z, REPEAT_STEPS, REPEAT_Z, noise_lag1, repeat_share
from .residual import RefitResidual, corrected, projector, radius, refit, with_time
from .spikes import (GLITCH_Z, P0_AXIS, TRAIN_MIN, TRAIN_READS, TRAIN_WINDOW, TRAIN_Z, find_glitches,
                     glitch_train, radial_fractions, size_quantiles, spikes, turn_blur)
from .stats import repeats
from .steps import ORDER, TwinReport, baseline_model, compare_steps, step_models, whitened

__all__ = [
    "BAND", "CV_GAIN", "DRAWS", "EVENT_EDGE", "EVENT_MIN", "EVENT_Z", "GLITCH_Z", "MAX_EVENTS", "NOISE_LAG1_MAX",
    "NOISE_LAG1_Z", "ORDER", "ORIENTATION_WORDS", "P0_AXIS", "REPEAT_STEPS", "REPEAT_Z", "TAKE_SEEDS", "TRAIN_MIN",
    "TRAIN_READS", "TRAIN_WINDOW", "TRAIN_Z", "Band", "Mismatch", "RefitResidual", "StepComparison", "TwinReport",
    "along_the_field", "baseline_model", "compare", "compare_steps", "corrected", "direction_words", "disturbances",
    "event_pairs", "find_glitches", "glitch_process", "glitch_train", "learn", "locate", "mismatches", "noise_lag1",
    "placements", "projector", "radial_fractions", "radius", "refit", "repeat_share", "repeats", "replayed",
    "size_quantiles", "spikes", "step_models", "turn_blur", "twin_directions", "twin_draw", "twin_draws",
    "twin_readings", "whitened", "with_time",
]
