"""What the twins say of a recording's noise and repeated reads: the correlation of successive
reads' noise (``noise_lag1``), the law its white noise and its wander follow (``noise_law``:
how heavy their tails are), the white noise less the glitches the detector missed, and the share of reads that
repeat the conversion before (``repeat_share``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...core.series import Series
from ...sim.model import SensorModel
from ...sim.noise_law import NoiseLaw
from . import stats as ts
from .draw import twin_directions, twin_draw, twin_readings
from .residual import refit, with_time
from .stats import repeats


NOISE_LAG1_Z = 2.0  # the recording's lag-1 correlation must lie this many twin σ from the twins' mean
NOISE_LAG1_MAX = 0.45  # a one-step moving average reaches ±0.5


def noise_lag1(model: SensorModel, series: Series, free: bool = True, seeds=tuple(range(101, 113))) -> float:
    """The correlation between successive reads' noise that brings the twins' lag-1
    correlation of the residual to the recording's — 0 (white) unless the recording's lies
    beyond NOISE_LAG1_Z of the twins' spread. Every other effect (wander, repeats, glitches)
    is already in the twins, so what is left at lag 1 is the noise's own: it moves the
    residual's lag-1 correlation by its share of the residual's variance. A gap the noise
    could close only with a correlation beyond NOISE_LAG1_MAX is left to the effects that made
    it (0)."""
    real = refit(model, series.field_ut, series.t_s, with_time(series), free)
    u = twin_directions(model, series)
    twins = [twin_draw(model, series, seed, free, u) for seed in seeds]
    twins = [x for x in twins if x is not None]
    if real is None or len(twins) < 2:
        return 0.0
    lag = np.array([ts.lag1(x.e) for x in twins])
    gap = ts.lag1(real.e) - float(np.mean(lag))
    if abs(gap) <= NOISE_LAG1_Z * float(np.std(lag, ddof=1)):
        return 0.0
    rho = gap * float(np.mean([np.var(x.e) for x in twins])) / max(_white_var(model, series, u), 1e-300)
    return float(rho) if abs(rho) <= NOISE_LAG1_MAX else 0.0  # beyond what the noise can carry: not the noise's


NOISE_TAIL_Z = 1.5  # the recording's tail ratio must lie this many twin σ above the twins' mean
LEVEL_SD_LEARN_MAX = 1.0  # nepers: the heaviest white noise learned (its own tail ratio 18 against 3.82)
WANDER_H_LEARN_MAX = 0.45  # the heaviest wander learned (its own tail ratio 15 against 3.82)
LAW_STEPS = 4  # at most this many secant steps per part of the law (each a set of twins)
NOISE_LAW_SEEDS = tuple(range(121, 131))


def noise_law(model: SensorModel, series: Series, free: bool = True, seeds=NOISE_LAW_SEEDS) -> NoiseLaw:
    """The noise law (``magcal.sim.noise_law``) whose twins have the recording's tails: first
    the white noise's, read in the first differences of the refitted residual (the slow wander
    cancels there), then the wander's, read in the residual itself (``stats.tail_ratio`` of
    each). Each part stays Gaussian unless the recording's tail ratio lies beyond
    NOISE_TAIL_Z of the twins' spread above their mean; it is then found by secant steps on the
    same seeds (the twins move smoothly with it). Every other effect (disturbances, glitches,
    the quantum) is already in the twins, so the tails left are the noise's own. A gap even the
    heaviest law learned cannot close is left to the effects that made it (that part
    Gaussian); lighter tails than a Gaussian's are left too: both parts only add tails."""
    real = refit(model, series.field_ut, series.t_s, with_time(series), free)
    if real is None:
        return NoiseLaw()
    u = twin_directions(model, series)

    def tails(law: NoiseLaw, of) -> np.ndarray:
        twins = [twin_draw(replace(model, noise_law=law), series, seed, free, u) for seed in seeds]
        return np.log([ts.tail_ratio(of(x.e)) for x in twins if x is not None])

    white = _match(lambda v: tails(NoiseLaw(level_sd=v), np.diff), np.log(ts.tail_ratio(np.diff(real.e))),
                   LEVEL_SD_LEARN_MAX, squared=True)
    h = _match(lambda v: tails(NoiseLaw(level_sd=white, wander_h=v), np.asarray), np.log(ts.tail_ratio(real.e)),
               WANDER_H_LEARN_MAX, squared=False)
    return NoiseLaw(level_sd=white, wander_h=h)


def _match(tails, target: float, top: float, squared: bool) -> float:
    """The value in [0, top] at which ``tails(value)`` (the twins' log tail ratios) have the
    mean ``target``: 0 unless ``target`` is beyond NOISE_TAIL_Z of the spread at 0 or when
    ``top`` falls short of it; else regula falsi, in value² when ``squared`` (a level_sd: the
    log tail ratio is nearly straight in it, a scale mixture's kurtosis being 3·exp(4·level_sd²))."""
    at0 = tails(0.0)
    if len(at0) < 2 or target <= float(np.mean(at0)) + NOISE_TAIL_Z * float(np.std(at0, ddof=1)):
        return 0.0
    tol, f_top = 0.25 * float(np.std(at0, ddof=1)), float(np.mean(tails(top)))
    if f_top < target:
        return 0.0  # beyond what this part of the noise can carry: not its own
    p = 2.0 if squared else 1.0
    (a, fa), (b, fb) = (0.0, float(np.mean(at0))), (top**p, f_top)
    x = a
    for _ in range(LAW_STEPS):
        x = a + (target - fa) * (b - a) / max(fb - fa, 1e-12)
        fx = float(np.mean(tails(x ** (1.0 / p))))
        if abs(fx - target) <= tol:
            break
        if fx < target:
            a, fa = x, fx
        else:
            b, fb = x, fx
    return float(x ** (1.0 / p))


def less_noise(model: SensorModel, series: Series, missed: float) -> tuple:
    """The white noise less the glitches the detector missed: those stayed in the residual the
    wander and its white floor were fitted to, and the twin draws them again as glitches (on
    rm3100 umich flight the twins' RMS came out above the recording's). Cut to no less than a
    tenth of its variance."""
    sigma, white = np.asarray(model.noise_ut), _white_var(model, series)
    if white <= 0 or missed <= 0:
        return model.noise_ut
    return tuple(float(v) for v in sigma * np.sqrt(max(white - missed, 0.1 * white) / white))


def _white_var(model: SensorModel, series: Series, u: np.ndarray | None = None) -> float:
    """The radial variance µT² of the model's white noise along the recording's directions
    (``u``: ``twin_directions``, when the caller has them)."""
    u = (twin_directions(model, series) if u is None else u) @ np.asarray(model.calibration.soft_iron)
    return float(np.mean(u * u @ np.asarray(model.noise_ut) ** 2))


# the repeats' gate, as wide as the comparison's band (and NOISE_LAG1_Z): at three σ a recording
# with a few repeats more than chance (qmc5883l tomisuarez filtered 3 in 22745 reads, twins 0;
# ardupilot MAG 41 in 2384, chance about 25) got none and its comparison then called them missing
REPEAT_Z = 2.0
REPEAT_STEPS = 3  # at most this many Newton steps of the repeat share (each a pair of twins)


def _twin_repeats(model: SensorModel, series: Series, seeds) -> float:
    """The share of repeated reads in ``model``'s twins of ``series`` (its glitches too: a
    glitch on a repeated read breaks the repeat, in the recording as in the twin)."""
    chans, u = with_time(series), twin_directions(model, series)
    return float(np.mean([np.mean(repeats(twin_readings(model, u, series.t_s, chans, seed)[0])) for seed in seeds]))


def repeat_share(model: SensorModel, series: Series, seeds=(1, 2)) -> float:
    """The share of reads that repeat the previous conversion (the host read before the next
    one was ready): the recording's share of exact repeats beyond what its twins without
    repeats make by chance (a coarse quantum and a still board repeat a reading too), when it
    passes that chance share by REPEAT_Z binomial σ (the recording's and the twins' own count
    both counted); else 0.

    That first share is low: the twins without repeats read the recording's repeated reads
    at the direction before them, where noise alone repeats a reading far more often than after
    a turn, so they overstate chance. The twins with the share replay fresh conversions there;
    their chance repeats beside the share's own (c) set the step towards the share that makes
    the twins repeat as often as the recording (Newton on s + (1 − s)·c). Without these steps
    the twins of five of the seven real recordings with repeats repeated 4–16 % fewer reads
    than their recordings."""
    n = len(series.field_ut)
    seen = float(np.mean(repeats(series.field_ut)))
    if seen == 0.0:
        return 0.0
    chance = _twin_repeats(replace(model, repeat_share=0.0), series, seeds)
    spread = np.sqrt(max(chance * (1.0 - chance), 1.0 / n) / n * (1.0 + 1.0 / len(seeds)))
    if seen <= chance + REPEAT_Z * spread:
        return 0.0
    share = min((seen - chance) / (1.0 - chance), 0.9)
    for _ in range(REPEAT_STEPS):
        made = _twin_repeats(replace(model, repeat_share=share), series, seeds)
        if abs(made - seen) < 1.0 / n:
            break
        c = max((made - share) / (1.0 - share), 0.0)
        share = float(np.clip(share + (seen - made) / (1.0 - c), 0.0, 0.9))
    return float(share)
