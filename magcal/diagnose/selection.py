"""Which tested terms earn a place in the model: significance, size, wander, held-out gain.

1. Holm's family-wise control over both test families (against the quadratic wander, and each
   channel against the rich wander); a channel significant against the rich wander at or above
   the practical floor, and at ``alpha`` against the quadratic wander, is *fast* (an
   intermittent current) and passes straight on.
2. The practical floor: an effect smaller than max(0.03 µT, 0.1 × noise) is not worth a term;
   soft iron must also move some gain by at least softiron.MIN_GAIN_DEVIATION.
3. The wander gate: a slow channel term (significant only against the quadratic wander) must
   explain at least channels.WANDER_RATIO × the slow offset wander it leaves unexplained.
   Every p-value here is already judged against the recording's twin (magcal.diagnose.null).
4. Held-out: drop, one at a time, any term whose removal does not hurt the held-out residual of
   the linearised model (interleaved time blocks, both models carrying the wander nuisance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import channels, softiron
from .design import Design
from .inference import heldout_sse, holm, pinv_sym

HELDOUT_INTERLEAVE = 4


def practical_floor_ut(noise_ut: float) -> float:
    """The smallest effect (RMS µT of its radial signature) worth a term in the model."""
    return max(0.03, 0.1 * noise_ut)


@dataclass(frozen=True)
class Significant:
    """After the tests: Holm's verdict per term, and which channels passed as fast."""

    rejected: dict  # effect → rejected against the quadratic wander (Holm over both families)
    fast: set  # channels significant against the rich wander, above the practical floor


def family(tests: dict, rich: dict, extra: dict | None = None) -> dict:
    """The p-values of Holm's family: both test families together, without the tests the design
    could not run at all (``untestable``: no direction of the term left once the other columns
    are fitted — a slow channel against the rich wander, say). Such a test's p is 1 whatever the
    data say; counted in the family it would only make every other test's threshold stricter.
    ``extra``: further hypotheses of the family (the joint test of a collinear pair,
    magcal.diagnose.collinear), name → p."""
    pvals = {g: r.p for g, r in tests.items() if not r.untestable}
    pvals.update({("rich", g): r.p for g, r in rich.items() if not r.untestable})
    pvals.update(extra or {})
    return pvals


def significant(tests: dict, rich: dict, alpha: float, floor_ut: float, extra: dict | None = None) -> Significant:
    """Holm's step-down over the family (``family``)."""
    rejected_all = holm(family(tests, rich, extra), alpha)
    # fast: significant against the rich wander (Holm), and on its own at alpha against the
    # quadratic one too (two views of the same term must agree; chance rarely fools both)
    fast = {g for g, r in rich.items()
            if rejected_all.get(("rich", g), False) and r.effect_rms_ut >= floor_ut and tests[g].p <= alpha}
    return Significant({g: rejected_all.get(g, False) for g in tests}, fast)


def above_floor(tests: dict, verdict: Significant, floor_ut: float, soft_size: tuple[float, float]) -> list:
    """Terms that are significant and large enough to matter (fast channels pass as they are).
    Soft iron is judged by the size of what the model would carry — the reference's soft iron
    along every direction the data determine (``soft_size``: RMS of its radial signature in µT
    and its largest gain deviation, softiron.fitted_size) — not by the part its test could tell
    apart from the nuisances."""
    out = []
    for g, r in tests.items():
        if g in verdict.fast:
            out.append(g)
            continue
        if not verdict.rejected[g]:
            continue
        if g == softiron.EFFECT:
            rms_ut, deviation = soft_size
            if rms_ut >= floor_ut and deviation >= softiron.MIN_GAIN_DEVIATION:
                out.append(g)
            continue
        if r.effect_rms_ut >= floor_ut:
            out.append(g)
    return out


def wander_gate(design: Design, chans: dict, survivors: list, fast: set, left_out: tuple = ()) -> tuple[list, dict]:
    """Real recordings wander slowly: a slow channel term must explain most of the block offsets
    (channels.wander_shares, channels.WANDER_RATIO). Returns the survivors that pass and, for
    each channel judged, (explained, unexplained) block-offset mean squares (µT²).
    ``left_out``: channel terms refused after the gate (magcal.diagnose.claims) — their columns
    are not fitted, so what they explained counts as the wander the others must beat (a drift
    whose halves disagree is wander, not a partner that took the wander off a temperature)."""
    judged = [g for g in survivors if g in design.candidates and g not in left_out]
    if not judged:
        return survivors, {}
    # the residual with everything but the channel terms fitted out (soft iron and the direction
    # harmonics would otherwise alias into block offsets under partial coverage). The wander
    # nuisance is not among the columns fitted: the gate is the contest between the channel and
    # a slow wander, so the channel's coefficient is the one that explains the block offsets by
    # itself. Fitted beside a quadratic wander, a slow channel (a 1.3-cycle temperature swing)
    # shares its trend with it, the split is poorly determined, and the wander's share counted
    # against the channel: true temperatures in simulations without any wander failed the gate.
    x = design.x[:, : design.n_before_wander]
    e = design.residual_ut
    out = [design.groups[g] for g in left_out if g in design.groups]
    fitted = np.setdiff1d(np.arange(x.shape[1]), np.concatenate(out) if out else np.zeros(0, int))
    colscale = np.sqrt(np.maximum((x[:, fitted] ** 2).sum(axis=0), 1e-300))
    xs = x[:, fitted] / colscale
    beta = np.zeros(x.shape[1])
    beta[fitted] = (pinv_sym(xs.T @ xs) @ (xs.T @ e)) / colscale
    chan_cols = [design.groups[g] for g in design.groups if g in design.candidates and g not in left_out]
    chan_cols = np.concatenate(chan_cols) if chan_cols else np.zeros(0, int)
    other = np.setdiff1d(np.arange(x.shape[1]), chan_cols)
    e_w = e - x[:, other] @ beta[other]
    cands = design.candidates
    shares, v_rem = channels.wander_shares(
        e_w,
        design.directions,
        {g: chans[cands[g].channel] - cands[g].reference for g in judged},
        {g: -beta[design.groups[g]] for g in judged},
    )
    shares_of = {g: (shares[g], v_rem) for g in judged}
    passed = [g for g in survivors if g not in shares or g in fast or shares[g] >= channels.WANDER_RATIO * v_rem]
    return passed, shares_of


def drop_by_heldout(design: Design, survivors: list, folds: int) -> tuple[list, dict]:
    """Drop, one at a time, any survivor whose removal does not hurt the held-out residual of
    the linearised model. The baseline columns and the wander nuisance are in every model; the
    direction harmonics are not (fitted on 90 % of a recording they extrapolate badly into the
    held-out block). Returns the accepted terms and the last held-out RMS per subset."""
    base_cols = np.concatenate([np.arange(design.n_jacobian), design.wander_cols])
    accepted = list(survivors)
    heldout = {}
    while accepted:
        subsets = {"_all": np.concatenate([base_cols] + [design.groups[g] for g in accepted])}
        for g in accepted:
            subsets[g] = np.concatenate([base_cols] + [design.groups[h] for h in accepted if h != g])
        heldout = heldout_sse(design.x, design.residual_ut, subsets, 2 * folds, HELDOUT_INTERLEAVE)
        worst = max(accepted, key=lambda g: -(heldout[g] - heldout["_all"]))
        if heldout[worst] - heldout["_all"] > 0:
            break
        accepted.remove(worst)
    return accepted, heldout
