"""The glitch process a recording's spikes imply: the rate (and the share along the field) at
which twins of the recording make its detector find as many spikes as the recording shows.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...core.series import Series
from ...sim.model import SensorModel
from .draw import twin_directions, twin_draws
from .residual import corrected, with_time
from .spikes import radial_fractions, spikes


GLITCH_SEEDS = (1, 2, 3, 4)


def _spike_counter(model: SensorModel, series: Series, seeds=GLITCH_SEEDS):
    """rate ↦ (mean number of spikes ``spikes`` finds, the radial variance µT² of the glitches
    it misses, the spikes' ``radial_fractions``) on twins of ``series`` whose glitches come at ``rate``. The twins' other random
    parts are drawn once and the glitches from fixed generators (common random numbers): a
    higher rate adds glitches where a lower one had them, so the count rises with the rate and
    a bracketing solve converges."""
    chans, u = with_time(series), twin_directions(model, series)
    bare = model.without("glitches")
    base = [twin_draws(bare, u, series.t_s, seed) for seed in seeds]  # (directions seen, draws) per seed
    seen = [v @ np.asarray(model.calibration.soft_iron) for v, _ in base]  # a jump g of m moves |h| by seen·g

    def count(rate: float) -> tuple[float, float, np.ndarray]:
        n_hit, missed, fractions = 0, 0.0, []
        for seed, (v, d), w in zip(seeds, base, seen):
            rng = np.random.default_rng([seed, 0x611])
            g, along = model.glitch_vectors(rng, series.t_s, seed, rate)
            m, _ = bare.distort(v, chans, replace(d, glitch_ut=g, glitch_along_ut=along))
            h = corrected(bare.calibration, m, chans)
            hit = spikes(m, radius=np.linalg.norm(h, axis=1), directions=v)
            n_hit += int(np.count_nonzero(hit))
            moved = np.sum(g * w, axis=1) + (0.0 if along is None else along)  # a glitch along the field moves |h| by its size
            missed += float(np.sum(moved[~hit] ** 2)) / len(v)
            fractions.append(radial_fractions(h, hit))
        return n_hit / len(seeds), missed / len(seeds), np.concatenate(fractions)

    return count


def _rate_for(count, observed: float, n: int, steps: int = 12, top: float | None = None) -> float | None:
    """The rate at which the twins' spike count equals ``observed`` (bisection; the count
    rises with the rate), or None when even a glitch in every other sample falls short (the
    sizes are too small for the detector to see); ``top``: the highest rate there is (a pulse
    train's every pulse), returned when the count falls short there."""
    ceiling = 0.5 if top is None else top
    lo, hi = 0.0, min(max(2.0 * observed / n, 1e-4), ceiling)
    while count(hi)[0] < observed:
        if hi >= ceiling:
            return top
        lo, hi = hi, min(2.0 * hi, ceiling)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if count(mid)[0] < observed else (lo, mid)
    return 0.5 * (lo + hi)


def glitch_process(model: SensorModel, series: Series, hit: np.ndarray) -> tuple[float, float]:
    """(rate per sample, the radial variance µT² of the glitches the detector misses) of the
    glitches, at the model's sizes, that make the twins' detector find as many spikes as it
    finds on the recording. The detector misses glitches near the noise and finds a few spikes
    where there are none (its false positives: the count on glitch-free twins), so the rate
    seen is not the rate to draw; both are measured on twins of the recording (its times,
    directions and every other effect) and the rate solved by bisection — no rate when the
    recording shows no more spikes than glitch-free twins make, within three Poisson σ. A pulse
    train cannot glitch more reads than it has pulses: when even a glitch at every pulse falls
    short, every pulse glitches (the nearest the train comes)."""
    rate, missed, _ = _process(model, series, hit)
    return rate, missed


def _process(model: SensorModel, series: Series, hit: np.ndarray) -> tuple[float, float, np.ndarray]:
    """``glitch_process`` and the ``radial_fractions`` of the spikes of its twins at that rate
    (``along_the_field`` needs them: from the same counter, not a second one drawn alike)."""
    observed = float(np.count_nonzero(hit))
    count = _spike_counter(model, series)
    _, _, fractions = null = count(0.0)
    if observed <= null[0] + 3.0 * np.sqrt(max(null[0], 1.0)):
        return 0.0, 0.0, fractions
    full = None if model.glitch_period_s is None else min(1.0 / (model.rate_hz * model.glitch_period_s), 0.5)
    rate = _rate_for(count, observed, len(hit), top=full)
    if rate is None:
        # the detector cannot place them: keep the rate it saw
        return model.glitch_rate, 0.0, count(model.glitch_rate)[2]
    _, missed, fractions = count(rate)
    return float(min(rate, 0.5)), missed, fractions


def along_the_field(model: SensorModel, series: Series, hit: np.ndarray, h: np.ndarray, missed: float,
                    sizes) -> tuple[SensorModel, float]:
    """(the model with the share of its glitches that lie along the field, the radial variance
    µT² of the glitches the detector misses). The spikes of |h| favour glitches along the field
    even when their directions are random, so the recording's mean ``radial_fractions`` (its
    spikes ``hit`` of the corrected readings ``h``) is set against the twins': at the model's
    rate with no glitch along the field, and with every glitch not on a sensor axis along it
    (``sizes(share)``: the size quantiles read for a share, the rate solved again); the share
    is interpolated between the two (none when the recording's mean is not above the first
    twins'; as the axis share, an estimate clipped to its range, with no test). A glitch along the field moves |h| by
    its whole length and the trajectory by no more, where a random one of the same departure
    in |h| is twice as long on average: drawn in random directions, such glitches gave the
    ArduPilot Solo twins isolated 3-vector jumps the recording lacks."""
    seen = radial_fractions(h, hit)
    if not len(seen) or model.glitch_rate <= 0:
        return model, missed
    none = _spike_counter(model, series)(model.glitch_rate)[2]
    if not len(none) or np.mean(seen) <= np.mean(none):
        return model, missed

    def solved(share: float) -> tuple[SensorModel, float, np.ndarray]:
        m = replace(model, glitch_radial_share=share, glitch_ut=sizes(share))
        rate, lost, fractions = _process(m, series, hit)
        return replace(m, glitch_rate=rate), lost, fractions

    top = 1.0 - model.glitch_axis_share
    full, lost, every = solved(top)
    if not len(every) or np.mean(every) <= np.mean(none):
        return full, lost
    share = top * float(np.clip((np.mean(seen) - np.mean(none)) / (np.mean(every) - np.mean(none)), 0.0, 1.0))
    if share >= top:
        return full, lost
    out, lost, _ = solved(share)
    return out, lost
