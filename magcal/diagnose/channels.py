"""Offsets that follow a channel: temperature, current, time, any other numeric covariate.

Model: b(x) = b₀ + K (x − x_ref), K three µT per unit of the channel (sensor frame). To first
order the radial residual of a fit without it is uᵀK(x − x_ref), so the candidate regressors
are (x − x_ref)·u (3 columns).

Temperature and time are confounded during a monotone warm-up (docs/physics.md, "Temperature and time"): when the
temperature history is explained by a straight line in time (|corr| ≥ CONFOUND_CORR) the two
cannot be told apart from one recording. Diagnosis then tests a single term and reports it as
``time_drift`` — the offset moved during the recording — with ``confounded_with: temp_c`` and
the equivalent µT/°C in the evidence, rather than guessing a temperature law that would be
applied (wrongly, if it is really drift) to future sessions. The same holds for any other
channel that only rises or falls during the recording (ambient temperature, humidity, a
discharging battery): each is folded into the one time term and named there, instead of all
of them being tested against one another, which leaves none testable.

``TERM`` is the effect as a row of the design's table (magcal.diagnose.design.CATALOGUE): one
tested group of three columns per candidate channel, named by ``effect_name``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre

from .catalogue import Accepted, CatalogueEffect, Columns, Linearised, Role
from .finding import Finding

TIME = "t_s"
TEMP = "temp_c"
CURRENT = "current_a"
CONFOUND_CORR = 0.95
# a slow channel term must explain at least 4× the (variance of the) slow offset wander it leaves
# unexplained, i.e. ≥ 80 % of it: one slow channel cycle otherwise matches real wander by chance
WANDER_RATIO = 4.0
# which directions of a channel term are tested: a channel term is linear in its coefficients, so
# unlike soft iron there is no valley along which a fit can slide, and a direction the other
# columns largely mimic is still determined by the part they do not — the Wald statistic weighs
# it by that information (its covariance), and the statistic does not grow as the part shrinks.
# Only directions with numerically no part of their own are left out. (A gate of a fifth of the
# column, as for soft iron, refused a 1.3-cycle temperature swing on a full sphere, 82-85 % of it
# a quadratic in time, with F = 36 for the whole term.)
MIN_UNIQUE = 1e-3

_EFFECT = {TEMP: "temperature_drift", CURRENT: "current_interference", TIME: "time_drift"}
_UNIT = {TEMP: "°C", CURRENT: "A", TIME: "s"}
_WHAT = {
    TEMP: "the die temperature",
    CURRENT: "the current in {name}",
    TIME: "time",
}


@dataclass(frozen=True)
class ChannelCandidate:
    channel: str
    effect: str
    reference: float
    confounded: tuple = ()  # ((channel, correlation with time), …) folded into this (time) term

    @property
    def confounded_with(self) -> str | None:
        return ", ".join(n for n, _ in self.confounded) or None

    @property
    def confound_corr(self) -> float | None:
        """The temperature's correlation with time when it is among them, else the first's."""
        if not self.confounded:
            return None
        return dict(self.confounded).get(TEMP, self.confounded[0][1])


def effect_name(channel: str) -> str:
    return _EFFECT.get(channel, f"covariate:{channel}")


def usable(x: np.ndarray) -> bool:
    x = np.asarray(x, np.float64)
    if not np.all(np.isfinite(x)):
        return False
    spread = np.ptp(x) if len(x) else 0.0
    return bool(spread > 1e-9 * max(1.0, np.max(np.abs(x))) and len(np.unique(x[: min(len(x), 20000)])) > 1)


def candidates(t_s: np.ndarray, channels: dict[str, np.ndarray]) -> tuple[list[ChannelCandidate], list[str]]:
    """The channel candidates for a recording, and the names of channels skipped (constant or
    with missing values)."""
    out: list[ChannelCandidate] = []
    skipped = []
    confounded = []
    time_ok = usable(t_s)
    for name, x in channels.items():
        if name == TIME:
            continue
        if not usable(x):
            skipped.append(name)
            continue
        if time_ok and name != CURRENT:
            c = float(np.corrcoef(x, t_s)[0, 1])
            if abs(c) >= CONFOUND_CORR:
                confounded.append((name, c))
                continue
        ref = 0.0 if name == CURRENT else float(np.mean(x))
        out.append(ChannelCandidate(name, effect_name(name), ref))
    if time_ok:
        confounded.sort(key=lambda nc: nc[0] != TEMP)  # the temperature first when it is there
        out.append(ChannelCandidate(TIME, effect_name(TIME), float(np.mean(t_s)), tuple(confounded)))
    return out, skipped


def regressors(x: np.ndarray, reference: float, m: np.ndarray, offset_ut: np.ndarray) -> np.ndarray:
    d = m - offset_ut
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    return -(np.asarray(x, np.float64) - reference)[:, None] * u


def describe(
    cand: ChannelCandidate,
    coef: np.ndarray,
    x: np.ndarray,
    t_s: np.ndarray,
    evidence: dict,
    temp: np.ndarray | None = None,
    clock: bool = True,
) -> Finding:
    name = cand.channel
    unit = unit_of(name, clock)
    size = float(np.linalg.norm(coef))
    contrib = np.abs((x - cand.reference)) * size
    peak = float(contrib.max()) if len(contrib) else 0.0
    hot = contrib >= 0.5 * peak if peak > 0 else np.zeros(len(x), bool)
    what = _WHAT.get(name, "the channel {name}").format(name=name)
    direction = coef / size if size > 0 else coef
    where = {
        "channel": name,
        "direction": [float(v) for v in direction],
        "range": [float(np.min(x)), float(np.max(x))],
        "strong_range": [float(np.min(x[hot])), float(np.max(x[hot]))] if hot.any() else None,
        "strong_time_s": [float(np.min(t_s[hot])), float(np.max(t_s[hot]))] if hot.any() else None,
        "strong_fraction": float(np.mean(hot)),
    }
    span = float(np.ptp(x)) * size
    if name == TIME:
        summary = (
            f"The offset drifted by {size:.3g} µT/{unit} ({span:.2f} µT over the recording) along "
            f"({_vec(direction)}): the hard iron is not constant in time."
        )
        if cand.confounded:
            names = [n for n, _ in cand.confounded]
            if names == [TEMP]:
                summary += (
                    " The temperature rose or fell monotonically with time here, so this drift cannot be "
                    "told apart from a temperature coefficient; record again with a non-monotone "
                    "temperature history to separate them."
                )
            else:
                summary += (
                    f" The channels {', '.join(names)} rose or fell monotonically with time here, so this drift "
                    "cannot be told apart from an effect of any of them; record again while they go up and "
                    "down to separate them."
                )
    elif name == TEMP:
        summary = (
            f"The offset moves with {what} by {size:.3g} µT/°C along ({_vec(direction)}): "
            f"{span:.2f} µT across the {np.ptp(x):.1f} °C seen, which a constant hard iron cannot follow."
        )
    elif name == CURRENT:
        summary = (
            f"A current adds its own field: {size:.3g} µT per A along ({_vec(direction)}), "
            f"{span:.2f} µT at the largest current seen, present only while the current flows."
        )
    else:
        summary = (
            f"The offset follows the channel {name!r} by {size:.3g} µT per unit along "
            f"({_vec(direction)}), {span:.2f} µT across its range: an unmodelled field source tied to it."
        )
    ev = dict(evidence)
    if cand.confounded_with:
        ev["confounded_with"] = cand.confounded_with
        ev["confound_corr"] = cand.confound_corr
        if temp is not None and np.ptp(temp) > 0 and TEMP in dict(cand.confounded):
            ev["equivalent_coef_ut_per_c"] = [float(v) for v in coef * np.ptp(x) / np.ptp(temp) * np.sign(cand.confound_corr)]
    return Finding(
        effect=cand.effect,
        summary=summary,
        where=where,
        evidence=ev,
        params={"channel": name, "coef_ut_per_unit": [float(v) for v in coef], "reference": cand.reference},
    )


def columns(lin: Linearised) -> Columns:
    """One group of three columns per candidate channel (in candidate order): the Jacobian's
    offset-per-unit columns at the reference, where the channel coefficients the reference was
    fitted with (``lin.coefs``) are taken back out of the residual to first order, so each
    test is still of its term being zero (design.build)."""
    jac = lin.jac_channels
    return Columns(jac, tuple((c.effect, 3) for c in lin.candidates), jac @ lin.coefs)


def finding(acc: Accepted) -> Finding:
    """An accepted channel term as a finding: its refitted coefficient, with that coefficient's
    interval added to the evidence (``acc.uncertainty``)."""
    cand = acc.candidates[acc.group]
    coef = acc.final.coef_ut_per_unit[cand.channel]
    ev = dict(acc.evidence)
    ev.update(acc.uncertainty(coef))
    return describe(cand, coef, acc.chans[cand.channel], acc.t_s, ev, acc.chans.get(TEMP), acc.clock)


TERM = CatalogueEffect("offset_versus_channel", Role.TESTED, columns, finding, MIN_UNIQUE)


def _vec(v: np.ndarray) -> str:
    return ", ".join(f"{x:+.2f}" for x in v)


def usable_blocks(n: int, n_blocks: int) -> list[slice]:
    """The contiguous time blocks a block offset is fitted in (those of at least 12 samples)."""
    from .inference import contiguous_blocks

    return [b for b in contiguous_blocks(n, n_blocks) if b.stop - b.start >= 12]


def _block_offsets(e: np.ndarray, u: np.ndarray, series: dict[str, np.ndarray], n_blocks: int):
    """Offsets δ_b fitted per contiguous time block (e ≈ uᵀδ_b) to the residual and to each of
    ``series`` (radial predictions), with each block's Gram matrix, the samples used and the
    within-block noise variance; None when there are fewer than 4 usable blocks."""
    blocks = usable_blocks(len(e), n_blocks)
    n = sum(b.stop - b.start for b in blocks)
    if len(blocks) < 4:
        return None
    grams, d_e, d_c, rss = [], [], {c: [] for c in series}, 0.0
    for b in blocks:
        a = u[b]
        g = a.T @ a
        inv = np.linalg.pinv(g)
        sol = inv @ (a.T @ e[b])
        rss += float(np.sum((e[b] - a @ sol) ** 2))
        grams.append(g)
        d_e.append(sol)
        for c, y in series.items():
            d_c[c].append(inv @ (a.T @ y[b]))
    s2 = rss / max(n - 3 * len(blocks), 1)
    return np.array(grams), np.array(d_e), {c: np.array(v) for c, v in d_c.items()}, n, s2


def _departures(grams: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Each block's squared offset departure from the blocks' weighted mean, in the sample
    domain (δᵀU_bᵀU_bδ, µT² summed over its samples): a block whose directions pin an offset
    only weakly counts only weakly."""
    mean = np.linalg.solve(grams.sum(axis=0), np.einsum("bij,bj->i", grams, d))
    dc = d - mean
    return np.einsum("bi,bij,bj->b", dc, grams, dc)


def _energy(grams: np.ndarray, d: np.ndarray, n: int) -> float:
    """Mean square (per sample) of block offsets about their weighted mean."""
    return float(np.sum(_departures(grams, d))) / n


def wander_shares(e: np.ndarray, u: np.ndarray, xs: dict[str, np.ndarray], coefs: dict[str, np.ndarray], n_blocks: int = 20):
    """How much of the recording's slow offset wander each channel term explains.

    The radial residual is split into contiguous time blocks and an offset δ_b fitted in each
    (e ≈ uᵀδ_b; the radius is global). The channel terms' predictions uᵀK_c x_c go through the
    same block fit. Returns ({name: mean-square its block offsets explain}, mean square left
    unexplained beyond what the noise alone gives), both µT². Real recordings wander
    (environment, 1/f noise); a channel term that explains less than what is left is a slow
    coincidence, not an effect."""
    fitted = _block_offsets(e, u, {c: (u @ coefs[c]) * x for c, x in xs.items()}, n_blocks)
    if fitted is None:
        return {c: 0.0 for c in xs}, float("inf")
    grams, d_e, pred, n, s2 = fitted
    rem = d_e - sum(pred.values())
    v_rem = max(_energy(grams, rem, n) - 3 * (len(grams) - 1) * s2 / n, 0.0)
    return {c: _energy(grams, p, n) for c, p in pred.items()}, v_rem


SLOW_DEGREE = 6  # a channel is "slow" when a degree-6 curve in time carries SLOW_SHARE of its variance
SLOW_SHARE = 0.8


def unit_of(channel: str, clock: bool = True) -> str:
    """The unit a coefficient of ``channel`` is per; time counts samples when the recording has
    no clock (its t_s is the sample index)."""
    return "sample" if channel == TIME and not clock else _UNIT.get(channel, "unit")


def slow_term_floor(x: np.ndarray, wander_rms_ut: float, ratio: float, n_blocks: int = 20) -> float | None:
    """The smallest coefficient (µT per unit of x, averaged over its direction) whose block
    offsets would carry ``ratio`` × the energy of a wander of ``wander_rms_ut`` — the size a
    slow term must reach before a recording that wanders this much can tell it apart (the
    wander gate). None when x is not slow (a fast channel such as an intermittent current is
    judged by the rich-wander test, not the gate) or does not vary; the sample index stands for
    time. A term uᵀk·x has block offsets k·x̄_b, and over directions of k its energy per sample
    is |k|²/3 · Σ_b n_b (x̄_b − x̄)² / n (|u| = 1)."""
    slow = _slow_blocks(x, n_blocks)
    if slow is None:
        return None
    _, nb, dev = slow
    between = float(np.sum(nb * dev**2) / nb.sum())
    return float(np.sqrt(ratio * 3.0 / between) * wander_rms_ut)


def slow_block_energy(x: np.ndarray, u: np.ndarray, n_blocks: int = 20) -> np.ndarray | None:
    """M = Σ_b (x̄_b − x̄)² G_b / n (G_b = Σ_{i∈b} u_iu_iᵀ): a slow term uᵀk·x has block-offset
    energy kᵀMk per sample. None when x is not slow (see ``slow_term_floor``)."""
    slow = _slow_blocks(x, n_blocks)
    if slow is None:
        return None
    blocks, nb, dev = slow
    u = np.asarray(u, np.float64)
    return sum(d**2 * (u[b].T @ u[b]) for b, d in zip(blocks, dev)) / nb.sum()


def slow_term_floor_range(x: np.ndarray, u: np.ndarray, wander_rms_ut: float, ratio: float,
                          n_blocks: int = 20) -> tuple[float, float | None] | None:
    """``slow_term_floor`` along the direction of k the motion pins best and the one it pins
    worst: a block's offset along k̂ is seen through its directions u (Gram matrix G_b = Σ uuᵀ),
    so the term's block-offset energy is k̂ᵀ M k̂ |k|² with M = Σ_b (x̄_b − x̄)² G_b / n, and the
    floor along k̂ is √(ratio / k̂ᵀMk̂) · wander. The mean over directions is ``slow_term_floor``."""
    m = slow_block_energy(x, u, n_blocks)
    if m is None:
        return None
    lam = np.linalg.eigvalsh(m)
    if lam[-1] <= 0:
        return None
    # None: along some direction the motion never pins the term, however large
    hi = float(np.sqrt(ratio / lam[0]) * wander_rms_ut) if lam[0] > 1e-9 * lam[-1] else None
    return float(np.sqrt(ratio / lam[-1]) * wander_rms_ut), hi


def _slow_blocks(x: np.ndarray, n_blocks: int):
    """(blocks, samples per block, block mean − overall mean) of a channel that varies slowly
    (a degree-SLOW_DEGREE curve in time carries SLOW_SHARE of its variance), else None."""
    from .inference import contiguous_blocks

    x = np.asarray(x, np.float64)
    total = float(np.var(x))
    if total <= 0 or len(x) < 4 * n_blocks:
        return None
    vand = legendre.legvander(np.linspace(-1.0, 1.0, len(x)), SLOW_DEGREE)
    smooth = vand @ np.linalg.lstsq(vand, x, rcond=None)[0]
    if np.var(smooth) < SLOW_SHARE * total:
        return None
    blocks = contiguous_blocks(len(x), n_blocks)
    nb = np.array([b.stop - b.start for b in blocks], np.float64)
    means = np.array([x[b].mean() for b in blocks])
    dev = means - np.sum(nb * means) / nb.sum()
    if not np.any(dev):
        return None
    return blocks, nb, dev


def offset_wander(e: np.ndarray, u: np.ndarray, n_blocks: int = 20) -> tuple[float, float]:
    """The offset's slow wander in a model's residual: (RMS beyond noise in µT, p-value of
    "no wander"). Under independent noise the block offsets' energy × n / σ² is χ² with
    3(B − 1) degrees of freedom (σ² from the scatter inside the blocks)."""
    return wander_size(block_wander(e, u, n_blocks))


def wander_size(w: "WanderBlocks | None") -> tuple[float, float]:
    """(RMS beyond noise in µT, p-value of "no wander") of the block offsets ``w``."""
    from ..fit.tails import chi2_sf

    if w is None:
        return 0.0, 1.0
    energy = float(np.sum(w.departure_ut2)) / w.n
    df = 3 * (len(w.blocks) - 1)
    v = max(energy - df * w.noise_ut2 / w.n, 0.0)
    return float(np.sqrt(v)), float(chi2_sf(energy * w.n / max(w.noise_ut2, 1e-300), df))


@dataclass(frozen=True)
class WanderBlocks:
    """The block offsets' departures behind ``offset_wander``: the blocks (sample slices), each
    one's squared departure (µT² summed over its samples), the samples used and the
    within-block noise variance (µT²), and the block offsets themselves with their Gram matrices."""

    blocks: tuple[slice, ...]
    departure_ut2: np.ndarray
    n: int
    noise_ut2: float
    offsets_ut: np.ndarray  # (B, 3) each block's fitted offset
    grams: np.ndarray  # (B, 3, 3) each block's Σ uuᵀ: how firmly its directions pin that offset


def block_wander(e: np.ndarray, u: np.ndarray, n_blocks: int = 20) -> WanderBlocks | None:
    """Where in time the offset wander of residual ``e`` sits, block by block; None when there
    are fewer than 4 usable blocks."""
    fitted = _block_offsets(e, u, {}, n_blocks)
    if fitted is None:
        return None
    grams, d_e, _, n, s2 = fitted
    return WanderBlocks(tuple(usable_blocks(len(e), n_blocks)), _departures(grams, d_e), n, s2, d_e, grams)
