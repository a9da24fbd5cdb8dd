"""What a diagnosis says: findings with their evidence, limits, the offset wander and floors.

Everything here describes results the ladder has computed (magcal.diagnose.ladder); nothing
here decides what is in the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from . import channels, design, floors, glitches, limits as limits_, longrun, selection, softiron, wander_jump
from ..fit.tails import chi2_sf, f_isf, t_isf
from .catalogue import Accepted
from .finding import Finding
from .limits import Limit
from .model import ModelFit

WANDER_BLOCKS = limits_.WANDER_BLOCKS


@dataclass(frozen=True)
class BlockWander:
    """The offset's slow wander in a model's residual (channels.offset_wander)."""

    rms_ut: float  # beyond the noise
    p_value: float  # of "no wander"
    directions: np.ndarray  # (n, 3) calibrated unit field directions
    stretches_s: tuple[tuple[float, float], ...] = ()  # where it concentrates ([start, end] in time)
    stretch_share: float = 0.0  # of the blocks' squared departure, the share those stretches carry
    jump: wander_jump.Jump | None = None  # most of it one change between two stretches of time


# the wander is said to sit somewhere when the fewest blocks that carry MOST_OF it (largest first)
# are at most CONCENTRATED_BLOCKS of them (half of it in 3 of 20 stretches: a smooth wander spreads wider),
# each beyond the noise at the diagnosis' α over all blocks
MOST_OF = 0.5
CONCENTRATED_BLOCKS = 0.15


def measure_wander(model: ModelFit, m: np.ndarray, chans: dict, t_s: np.ndarray, alpha: float) -> BlockWander:
    """Offsets fitted in WANDER_BLOCKS time blocks of ``model``'s residual, their scatter
    beyond the within-block noise, the stretches of time where it concentrates and the one
    jump that carries most of it (magcal.diagnose.wander_jump)."""
    used = {c: chans[c] for c in model.spec.channels}
    h = model.calibration().correct(m, used)
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    e = model.residual(m, used)
    blocks = channels.block_wander(e, u, WANDER_BLOCKS)
    rms, p = channels.wander_size(blocks)
    if blocks is None:
        return BlockWander(rms, p, u)
    t = np.asarray(t_s, float)
    jump = wander_jump.find_jump(blocks, t, alpha)
    if jump is not None:  # most of it one change: the blocks either side of it depart, which is no stretch of its own
        return BlockWander(rms, p, u, jump=jump)
    return BlockWander(rms, p, u, *_concentration(blocks, t, alpha))


def _concentration(w: channels.WanderBlocks, t: np.ndarray, alpha: float) -> tuple[tuple, float]:
    """The stretches (runs of adjacent blocks) that carry most of the blocks' squared offset
    departure when few blocks do, with the share they carry; nothing when it is spread."""
    dep = w.departure_ut2
    order = np.argsort(dep)[::-1]
    k = int(np.searchsorted(np.cumsum(dep[order]), MOST_OF * float(np.sum(dep)))) + 1
    hot = order[:k]
    beyond = chi2_sf(dep[hot] / max(w.noise_ut2, 1e-300), 3) < alpha / len(dep)
    if k > CONCENTRATED_BLOCKS * len(dep) or not np.all(beyond):
        return (), 0.0
    runs: list[list[int]] = []
    for i in np.sort(hot):
        if runs and runs[-1][-1] == i - 1:
            runs[-1].append(int(i))
        else:
            runs.append([int(i)])
    stretches = tuple((float(t[w.blocks[r[0]].start]), float(t[w.blocks[r[-1]].stop - 1])) for r in runs)
    return stretches, float(np.sum(dep[hot]) / max(np.sum(dep), 1e-300))


def accepting_test(g: str, selected):
    """The test that accepted term g (the rich-wander one for a fast channel)."""
    return selected.rich[g] if g in selected.fast else selected.tests[g]


def estimating_test(g: str, selected):
    """The test whose regression gives term g's coefficient and its covariance: the one with
    the quadratic wander as nuisance, whichever test accepted the term (against the rich
    wander a fast channel is tested well but its coefficient shares more with the nuisance)."""
    return selected.tests[g]


def envelope(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The covariance that is a along every direction where a is the larger and b where b is:
    b's eigenvalues in a's whitened coordinates raised to at least 1."""
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    root = v * np.sqrt(np.maximum(w, 1e-300))
    inv = v / np.sqrt(np.maximum(w, 1e-300))
    mw, mv = np.linalg.eigh(inv.T @ (0.5 * (b + b.T)) @ inv)
    return root @ (mv * np.maximum(mw, 1.0)) @ mv.T @ root.T


def widened(cov: np.ndarray, spread: np.ndarray | None, inflation: float = 1.0,
            slow: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The test's covariance scaled up (never down) by the larger of the test's twin inflation λ
    (inference.calibrated: the test's statistic is divided by it and its floor raised by it, so
    the region, the same test inverted, carries it too) and the draws' own coefficient spread
    over it, tr(V⁻¹ S) / k; then, along every direction where it is larger, ``slow``: the
    coefficient's covariance under the recording's own slow wander, which the block covariance
    cannot see where the term takes it (magcal.diagnose.longrun): (covariance, tr(V⁻¹ widened) / k)."""
    k = cov.shape[0]
    factor = max(1.0, float(inflation))
    prec = np.linalg.pinv(cov, rcond=1e-10, hermitian=True)
    if spread is not None:
        factor = max(factor, float(np.trace(prec @ spread)) / k)
    out = cov * factor
    if slow is not None:
        out = envelope(out, slow)
    return out, float(np.trace(prec @ out)) / k


def interval(coef: np.ndarray, result, slow=None) -> dict:
    """The 95 % uncertainty of a channel coefficient from the block-HAC covariance of its test,
    widened by the test's twin inflation λ, or to the coefficient's spread over the twin's draws
    where that is larger (see ``widened``: the draws carry the recording's own wander, which a
    covariance estimated from a few blocks can miss), and to the test's covariance plus the
    recording's own slow wander's share where that is larger (``slow``, a
    magcal.diagnose.longrun.SlowShare); per axis (Student t) and as a joint region
    (c − ĉ)ᵀ V⁻¹ (c − ĉ) ≤ ``coef_region95_wald``, with ν, the effective number of blocks, as
    degrees of freedom — or, with the wander's share, Satterthwaite's combination of ν and the
    degrees of freedom of the wander's fitted spectrum."""
    if result.cov is None:
        return {}
    nu = float(result.nu)
    k, df2 = result.df1, float(result.df2)
    cov, factor = widened(result.cov, result.null_spread, result.inflation, None if slow is None else slow.cov)
    if slow is not None:
        slow_k = float(np.trace(np.linalg.pinv(result.cov, rcond=1e-10, hermitian=True) @ slow.cov))
        share = slow_k / (slow_k + k)
        nu = 1.0 / ((1.0 - share) ** 2 / max(nu, 1.0) + share**2 / slow.dof)
        df2 = max(nu - k + 1.0, 1.0)
    half = float(t_isf(0.025, max(nu, 1.0))) * np.sqrt(np.maximum(np.diag(cov), 0.0))
    return {
        "coef_ut_per_unit_tested": [float(v) for v in -result.beta],
        "coef_ci95_ut_per_unit": [[float(c - h), float(c + h)] for c, h in zip(coef, half)],
        "coef_cov_ut_per_unit": [[float(v) for v in row] for row in cov],
        "coef_region95_wald": float(k * nu / df2 * f_isf(0.05, k, df2)),
        "coef_cov_widened_by": factor,
    }


def _evidence(g: str, selected, alpha: float, floor_ut: float) -> dict:
    """The statistics behind one accepted term (a finding's ``evidence``)."""
    r = accepting_test(g, selected)
    fast = g in selected.fast
    nuisance = (f"slow offset wander up to degree {design.RICH_DEGREE} in time" if fast
                else "quadratic offset wander in time" if selected.wander_nuisance
                else "no offset wander (the residual shows none)")
    ev = {
        "test": "Wald, block-HAC (batch means over contiguous time blocks, bias-corrected for the fitted "
        "nuisance columns), Holm-controlled, with a " + nuisance + " as a nuisance, "
        + (f"judged against {selected.null.count} draws of the recording's twin" if selected.null.count
           else f"referred to the F distribution ({selected.null.why_not})"),
        "F": r.f,
        "df": [r.df1, r.df2],
        "p_value": r.p,
        "alpha_familywise": alpha,
        "effect_rms_ut": r.effect_rms_ut,
        "practical_floor_ut": floor_ut,
        "heldout_rms_ut_with": selected.heldout.get("_all"),
        "heldout_rms_ut_without": selected.heldout.get(g),
    }
    ev["twin_inflation"] = r.inflation
    if selected.pair is not None and selected.pair.chosen == g:
        ev["collinear_pair"] = selected.pair.to_dict()
    if r.fallback:
        ev["test_fallback"] = r.fallback
    if g in selected.wander:
        ev["block_offset_rms_ut_explained"] = float(np.sqrt(selected.wander[g][0]))
        ev["block_offset_rms_ut_unexplained"] = float(np.sqrt(selected.wander[g][1]))
    return ev


def findings(a, selected, final: ModelFit, base: ModelFit, alpha: float, noise_ut: float) -> tuple:
    """The findings: glitches (if any), then each accepted term with its evidence, described by
    its effect (magcal.diagnose.catalogue: the design's table)."""
    out: list[Finding] = []
    if a.outlier.any():
        idx = a.glitches.index
        radial = base.residual(a.series.field_ut[idx], {})
        out.append(glitches.describe(a.glitches, a.series.row[idx], a.series.t_s[idx], radial))
    floor_ut = selection.practical_floor_ut(noise_ut)
    slow = slow_wander(a, selected)
    for g in selected.accepted:
        told = Accepted(g, final, _evidence(g, selected, alpha, floor_ut), a.chans, a.t, a.series.clock,
                        selected.candidates, partial(_interval_of, g, selected, slow))
        out.append(selected.design.effects[g].describe(told))
    return tuple(out)


def _interval_of(g: str, selected, slow: dict, coef: np.ndarray) -> dict:
    """Term g's coefficient ``coef`` with its interval (``interval``) from the test that estimated it."""
    return interval(coef, estimating_test(g, selected), slow.get(g))


def slow_wander(a, selected) -> dict:
    """Per accepted channel term: its coefficient's covariance from the recording's own slow
    wander (magcal.diagnose.longrun), with every column of the design in place."""
    dsg = selected.design
    groups = {g: dsg.groups[g] for g in selected.accepted if g in dsg.candidates}
    left_out = [dsg.groups[g] for g in dsg.candidates if g not in selected.accepted]
    model_cols = np.setdiff1d(np.arange(dsg.x.shape[1]), np.concatenate(left_out)) if left_out else np.arange(dsg.x.shape[1])
    _, t_kept, _ = a.kept
    return longrun.wander_covariances(dsg.x, dsg.residual_ut, t_kept, dsg.offset_directions, groups, model_cols)


def channel_floors(selected, wander: BlockWander, chans: dict, alpha: float, noise_ut: float) -> dict:
    """Per candidate channel not in the model: the size a term of it must reach to be reported
    (magcal.diagnose.floors), with the full calibration model in place."""
    alpha_each = alpha / max(selected.n_tests, 1)
    floor_ut = selection.practical_floor_ut(noise_ut)
    dsg = selected.design
    out = {}
    for g, cand in selected.candidates.items():
        if g in selected.accepted:
            continue
        x = chans[cand.channel] - cand.reference
        practical = floors.practical_floor(x, dsg.offset_directions, floor_ut)
        energy = channels.slow_block_energy(chans[cand.channel], wander.directions, WANDER_BLOCKS)
        gate = floors.gate_floor(energy, wander.rms_ut, channels.WANDER_RATIO) if wander.rms_ut > 0 else practical * 0
        test = selected.tests.get(g)
        slow = [floors.wald_floor(test, alpha_each), practical, gate]
        fast = []
        if g in selected.rich:
            fast = [floors.wald_floor(selected.rich[g], alpha_each), practical, floors.wald_floor(test, alpha)]
        out[cand.channel] = floors.combine(fast, slow)
    return out


def limits(a, selected, final: ModelFit, simulated_rms_ut: float, wander: BlockWander, *, alpha: float,
           located: tuple = ()) -> tuple[Limit, ...]:
    """What the recording ``a`` could not test: soft iron (``final``'s residual against the
    ``simulated_rms_ut`` it predicts for the noise says whether it is suspected), channels no
    test could reach, and the offset ``wander`` when it exceeds the noise at ``alpha`` (``located``:
    the names of what the locate step found, which the wander's statement cites)."""
    duration_s = float(a.t[-1] - a.t[0])
    found_soft = softiron.EFFECT in selected.accepted
    determined = selected.design.reference.spec.n_soft
    out = limits_.soft_iron_limits(selected.tests[softiron.EFFECT], found_soft, determined, final.rms_ut,
                                   simulated_rms_ut, duration_s)
    out += limits_.untested_channels(selected.tests, selected.candidates)
    left = [selected.candidates[g].channel for g in selected.candidates if g not in selected.accepted]
    floor_ut = selection.practical_floor_ut(a.glitches.noise_ut)
    _, _, chans_kept = a.kept
    return out + limits_.wander_limit(wander, chans_kept, alpha, floor_ut, left, a.series.clock, located)


def left_out(channels_left_out: tuple) -> tuple[Limit, ...]:
    """One limit per channel the screen left out (magcal.diagnose.hygiene), saying why."""
    return tuple(
        Limit(
            channels.effect_name(c.channel),
            False,
            f"An offset following {c.channel} could not be tested: {c.why}, so an offset that "
            "followed it would be a direction-dependent error, which hard and soft iron already model; "
            "left out of the candidates (name the channels with --channels to test it anyway).",
            c.channel,
            c.kind or "it follows the board's orientation",
            {"orientation_share": float(c.orientation_share)},
        )
        for c in channels_left_out
    )


def tests_record(selected) -> dict:
    """The intermediate statistics (``Diagnosis.tests``; not part of the JSON)."""
    rich = {
        g: {"F": r.f, "p": r.p, "effect_rms_ut": r.effect_rms_ut, "accepted_as_fast": g in selected.fast,
            "twin_inflation": r.inflation}
        for g, r in selected.rich.items()
    }
    candidates = {
        g: {"F": r.f, "p": r.p, "effect_rms_ut": r.effect_rms_ut, "twin_inflation": r.inflation,
            "coef_ut_per_unit": -r.beta if g in selected.candidates else None}
        for g, r in selected.tests.items()
    }
    return {"skipped_channels": selected.skipped, "twin_null": selected.null.to_dict(), "n_tests": selected.n_tests,
            "against_rich_wander": rich, "survivors": list(selected.survivors),
            "wander_nuisance": selected.wander_nuisance, "heldout": dict(selected.heldout), "candidates": candidates,
            "collinear": None if selected.pair is None else selected.pair.to_dict()}
