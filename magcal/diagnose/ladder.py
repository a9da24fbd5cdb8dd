"""The diagnosis ladder: fit, simulate, compare, locate, name, model, refit, show.

1. Gates: valid, finite samples only; glitches found from the smoothness of the 3-vector
   trajectory (magcal.diagnose.glitches) and set aside.
2. Baseline: hard iron + radius (the sphere), fitted on the rest.
3. Candidates: soft iron (5 degree-2 regressors) and one offset-vs-channel term per auxiliary
   channel and for time, tested jointly at the baseline by a block-HAC Wald test, with Holm's
   family-wise control at ``alpha``; degree-3/4 direction harmonics and a quadratic offset
   wander in time are nuisance terms in every test (magcal.diagnose.harmonics, .wander).
   Each channel is also tested against a rich wander (offset vs time up to degree
   RICH_DEGREE), its statistic calibrated against the same test of the channel circularly
   shifted out of alignment (inference.shift_inflation); Holm runs over both families together.
4. An effect earns its place only if it is also larger than a practical floor (µT relative to
   the recording's own noise) and improves the held-out residual (interleaved time blocks,
   both models carrying the wander nuisance). A channel that is significant only in the first
   family (it varies as slowly as the wander) must also explain at least 80 % of the slow
   offset wander (offsets fitted per time block) it is offered; one that stays significant
   against the rich wander (an intermittent current) needs no such gate.
5. The accepted terms are refitted jointly (nonlinear least squares on the radial residual)
   and the held-out RMS of baseline and final models reported.
6. Simulation vs recording: the fitted model, driven with the recording's own directions,
   timing and channels plus the measured noise, predicts the residual RMS a correct model
   would leave; both models are compared with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from ..core.errors import InputError
from ..core.series import Series
from . import channels as ch
from . import glitches as gl
from . import harmonics
from . import softiron as si
from . import wander as wd
from .finding import Finding
from .inference import _pinv_sym, block_wald, contiguous_blocks, heldout_sse, holm, shift_inflation
from .model import FitFailure, ModelFit, Spec, fit_model

ALPHA = 0.01
FOLDS = 5
MIN_SAMPLES = 50
MAX_ANALYSED = 200_000
# a channel term must explain at least 4× the (variance of the) slow offset wander it leaves
# unexplained, i.e. ≥ 80 % of it: one slow channel cycle otherwise matches real wander by chance
WANDER_RATIO = 4.0
# the slow wander as a nuisance (magcal.diagnose.wander): Legendre degrees 2..WANDER_DEGREE of
# the offset versus time, in every test and held-out comparison; with it, no wander gate
WANDER_DEGREE = 2
WANDER_GATE = True
RICH_DEGREE = 12
RICH_MAX = 50_000
HELDOUT_INTERLEAVE = 4
SHIFTS = 63  # circular shifts calibrating the rich-wander test of a channel (shift_inflation)


@dataclass(frozen=True)
class Diagnosis:
    n_samples: int
    baseline: ModelFit
    final: ModelFit
    findings: tuple[Finding, ...]
    baseline_heldout_rms_ut: float
    final_heldout_rms_ut: float
    simulated_rms_ut: float
    noise_ut: float
    series: Series = field(repr=False)  # the analysed samples (valid, finite)
    outlier_mask: np.ndarray = field(repr=False)
    tests: dict = field(default_factory=dict, repr=False)
    folds: tuple = field(default=(), repr=False)
    fold_rms: tuple = field(default=(), repr=False)  # ((baseline, final) per fold)
    limits: tuple = ()  # what this recording could not test, and whether it is suspected (dicts)

    @property
    def effects(self) -> list[str]:
        return [f.effect for f in self.findings]

    def model_name(self, fit: ModelFit) -> str:
        parts = ["sphere"]
        if fit.spec.soft_iron:
            parts = ["ellipsoid"]
        parts += [f"{c}" for c in fit.spec.channels]
        return "+".join(parts)

    def to_dict(self) -> dict:
        cal = self.final.calibration()
        reference = {ch.TEMP: float(cal.reference.get(ch.TEMP, 0.0)), ch.CURRENT: 0.0}
        reference.update({k: float(v) for k, v in cal.reference.items()})
        if ch.TEMP not in cal.reference:
            reference.pop(ch.TEMP)
        calib = {
            "offset_ut": [float(v) for v in cal.offset_ut],
            "field_ut": float(cal.field_ut),
            "soft_iron": [[float(v) for v in row] for row in cal.soft_iron],
            "reference": reference,
        }
        if cal.coef_ut_per_unit:
            calib["coef_ut_per_unit"] = {k: [float(x) for x in v] for k, v in cal.coef_ut_per_unit.items()}
        return {
            "n_samples": int(self.n_samples),
            "baseline": {
                "model": "sphere",
                "rms_ut": float(self.baseline.rms_ut),
                "heldout_rms_ut": float(self.baseline_heldout_rms_ut),
            },
            "findings": [f.to_dict() for f in self.findings],
            "final": {
                "model": self.model_name(self.final),
                "rms_ut": float(self.final.rms_ut),
                "heldout_rms_ut": float(self.final_heldout_rms_ut),
                "simulated_rms_ut": float(self.simulated_rms_ut),
            },
            "noise_ut": float(self.noise_ut),
            "limits": [dict(x) for x in self.limits],
            "calibration": calib,
        }


def _prepare(series: Series) -> Series:
    s = series.only_valid()
    ok = np.all(np.isfinite(s.field_ut), axis=1) & np.isfinite(s.t_s)
    if not ok.all():
        s = s.take(ok)
    if len(s) and np.any(np.diff(s.t_s) < 0):
        s = s.take(np.argsort(s.t_s, kind="stable"))
    if len(s) < MIN_SAMPLES:
        raise InputError(f"diagnosis needs at least {MIN_SAMPLES} valid samples, the recording has {len(s)}")
    return s


def _require(fit, what: str) -> ModelFit:
    if isinstance(fit, FitFailure):
        raise InputError(f"cannot fit the {what}: {fit.message}")
    return fit


def _practical_floor_ut(noise_ut: float) -> float:
    return max(0.03, 0.1 * noise_ut)


def diagnose(series: Series, alpha: float = ALPHA, folds: int = FOLDS) -> Diagnosis:
    """Model discovery on one recording (see the module docstring for the ladder)."""
    s = _prepare(series)
    m, t = s.field_ut, s.t_s
    n = len(s)
    glitch = gl.detect(m, t, alpha=alpha)
    outlier = np.zeros(n, bool)
    outlier[glitch.index] = True
    keep = ~outlier
    noise = glitch.noise_ut
    # a long recording is analysed on a systematic (time-ordered) subsample: glitches are
    # searched in every sample, and MAX_ANALYSED samples already pin every parameter far
    # below the noise
    sub = np.arange(n) if n <= MAX_ANALYSED else np.linspace(0, n - 1, MAX_ANALYSED).round().astype(np.int64)
    m, t, keep = m[sub], t[sub], keep[sub]
    chans_src = {k: v[sub] for k, v in s.channels.items()}
    n_a = len(sub)

    baseline = _require(fit_model(m, {}, Spec()), "sphere")
    mk, tk = m[keep], t[keep]
    chans_all = dict(chans_src)
    chans_all[ch.TIME] = t
    chk = {k: v[keep] for k, v in chans_all.items()}
    base0 = _require(fit_model(mk, {}, Spec(), start=baseline), "sphere")

    # -- candidates at the baseline -----------------------------------------------------------
    cands, skipped = ch.candidates(t, chans_src)
    e0, j0 = base0.jacobian(mk, {})
    cols = [j0]
    groups: dict[str, np.ndarray] = {}
    k = j0.shape[1]
    soft_x = si.regressors(mk, base0.offset_ut)
    cols.append(soft_x)
    groups[si.EFFECT] = np.arange(k, k + 5)
    k += 5
    by_effect = {}
    for c in cands:
        x = ch.regressors(chk[c.channel], c.reference, mk, base0.offset_ut)
        cols.append(x)
        groups[c.effect] = np.arange(k, k + 3)
        by_effect[c.effect] = c
        k += 3
    d0 = mk - base0.offset_ut
    u0 = d0 / np.linalg.norm(d0, axis=1, keepdims=True)
    cols.append(harmonics.regressors(u0))  # nuisance
    n_harm = cols[-1].shape[1]
    nuis = wd.regressors(tk, u0, WANDER_DEGREE)
    cols.append(nuis)  # nuisance: the slow offset wander
    xmat = np.concatenate(cols, axis=1)
    wander_cols = np.arange(k + n_harm, xmat.shape[1])
    tests = block_wald(xmat, e0, groups)
    # each channel is tested a second time against a rich wander nuisance (Legendre degrees
    # 2..RICH_DEGREE of the offset vs time): a channel that varies faster than the wander (an
    # intermittent current) keeps most of its variation and needs no wander gate; a slow one
    # (a temperature cycle) is absorbed and left to the first test and the gate. Holm runs
    # over both families together.
    rich = {}
    inflation: dict[str, float] = {}
    # time itself is the slowest channel: a straight line is what wander and drift share, so
    # time_drift always goes through the wander gate
    chan_groups = {g: c for g, c in groups.items() if g != si.EFFECT and by_effect[g].channel != ch.TIME}
    if chan_groups and RICH_DEGREE >= 2:
        # on a systematic subsample of at most RICH_MAX rows: the wide design stays small in memory
        sel = slice(None, None, max(1, -(-len(e0) // RICH_MAX)))
        x_rich = np.concatenate([xmat[sel, : k + n_harm], wd.regressors(tk[sel], u0[sel], RICH_DEGREE)], axis=1)
        rich = block_wald(x_rich, e0[sel], chan_groups)
        # calibrate each channel that could pass against its own circular shifts (a channel
        # switching on the scale of the residual's own fast structure otherwise over-rejects)
        for g in chan_groups:
            if rich[g].p > alpha:
                continue
            c = by_effect[g]
            xg = chk[c.channel][sel]
            lags = np.unique((np.linspace(0.05, 0.95, SHIFTS) * len(xg)).round().astype(int))
            shifted = (ch.regressors(np.roll(xg, lag), c.reference, mk[sel], base0.offset_ut) for lag in lags)
            # the aligned columns stay in the design: the shifted copies are judged on the
            # residual the channel leaves, so an effect that is there does not inflate its own null
            lam = shift_inflation(x_rich, e0[sel], shifted)
            inflation[g] = lam
            if lam > 1.0:
                p_cal = float(stats.f.sf(rich[g].f / lam, rich[g].df1, rich[g].df2))
                rich[g] = replace(rich[g], p=max(rich[g].p, p_cal))
        del x_rich
    pvals = {g: r.p for g, r in tests.items()}
    pvals.update({("rich", g): r.p for g, r in rich.items()})
    rejected_all = holm(pvals, alpha)
    rejected = {g: rejected_all[g] for g in tests}
    fast = {g for g, r in rich.items() if rejected_all[("rich", g)] and r.effect_rms_ut >= _practical_floor_ut(noise)}
    floor = _practical_floor_ut(noise)

    survivors = []
    for g, r in tests.items():
        if g in fast:
            survivors.append(g)
            continue
        if not rejected[g] or r.effect_rms_ut < floor:
            continue
        if g == si.EFFECT:
            w_lin = np.eye(3) + np.tensordot(r.beta, si.SOFT_BASIS, axes=1)
            if np.any(np.linalg.eigvalsh(w_lin) <= 0) or si.max_deviation(w_lin) < si.MIN_GAIN_DEVIATION:
                continue
        survivors.append(g)

    # real recordings wander slowly: a channel term must explain most of the block offsets
    # (channels.wander_shares, WANDER_RATIO)
    chan_surv = [g for g in survivors if g != si.EFFECT]
    wander = {}
    if chan_surv and WANDER_GATE:
        # the residual with everything but the channel terms fitted out (soft iron and the
        # direction harmonics would otherwise alias into block offsets under partial coverage)
        colscale = np.sqrt(np.maximum((xmat * xmat).sum(axis=0), 1e-300))
        xsc = xmat / colscale
        beta_all = (_pinv_sym(xsc.T @ xsc) @ (xsc.T @ e0)) / colscale
        chan_cols = np.concatenate([groups[g] for g in groups if g != si.EFFECT]) if len(groups) > 1 else np.zeros(0, int)
        other = np.setdiff1d(np.arange(xmat.shape[1]), np.concatenate([chan_cols, wander_cols]))
        e_w = e0 - xmat[:, other] @ beta_all[other]
        shares, v_rem = ch.wander_shares(
            e_w,
            d0 / np.linalg.norm(d0, axis=1, keepdims=True),
            {g: chk[by_effect[g].channel] - by_effect[g].reference for g in chan_surv},
            {g: -beta_all[groups[g]] for g in chan_surv},
        )
        wander = {g: (shares[g], v_rem) for g in chan_surv}
        survivors = [g for g in survivors if g == si.EFFECT or g in fast or shares[g] >= WANDER_RATIO * v_rem]

    # held-out comparisons: baseline columns + candidates (the 16 nuisance harmonics are left
    # out here: fitted on 90 % of a recording they extrapolate badly into the held-out block)
    base_cols = np.concatenate([np.arange(j0.shape[1]), wander_cols])
    accepted = list(survivors)
    cv = {}
    # drop, one at a time, any survivor whose removal does not hurt the held-out residual
    while accepted:
        full_cols = np.concatenate([base_cols] + [groups[g] for g in accepted])
        subsets = {"_all": full_cols}
        for g in accepted:
            subsets[g] = np.concatenate([base_cols] + [groups[h] for h in accepted if h != g])
        cv = heldout_sse(xmat, e0, subsets, 2 * folds, HELDOUT_INTERLEAVE)
        worst = max(accepted, key=lambda g: -(cv[g] - cv["_all"]))
        if cv[worst] - cv["_all"] > 0:
            break
        accepted.remove(worst)

    soft_dirs = None
    if si.EFFECT in accepted and tests[si.EFFECT].basis.shape[1] < 5:
        soft_dirs = tuple(map(tuple, tests[si.EFFECT].basis))
    spec = Spec(
        soft_iron=si.EFFECT in accepted,
        channels=tuple(by_effect[g].channel for g in accepted if g != si.EFFECT),
        soft_dirs=soft_dirs,
    )
    reference = {by_effect[g].channel: by_effect[g].reference for g in accepted if g != si.EFFECT}
    final = fit_model(mk, chk, spec, reference, start=base0)
    if isinstance(final, FitFailure):  # fall back to the baseline rather than a half-built model
        final, accepted, spec = base0, [], Spec()

    # -- held-out, nonlinear, contiguous blocks ----------------------------------------------
    fold_slices = contiguous_blocks(n_a, folds)
    sse_b = sse_f = 0.0
    n_eval = 0
    fold_rms = []
    for f in fold_slices:
        train = np.ones(n_a, bool)
        train[f] = False
        test = ~train & keep
        fb = fit_model(m[train], {}, Spec(), start=baseline)
        ff = fit_model(m[train & keep], {c: v[train & keep] for c, v in chans_all.items()}, spec, reference, start=final)
        if not fb or not ff or not test.any():
            continue
        rb = fb.residual(m[test], {})
        rf = ff.residual(m[test], {c: v[test] for c, v in chans_all.items()})
        sse_b += rb @ rb
        sse_f += rf @ rf
        n_eval += int(test.sum())
        fold_rms.append((float(np.sqrt(np.mean(rb**2))), float(np.sqrt(np.mean(rf**2)))))
    hb = float(np.sqrt(sse_b / n_eval)) if n_eval else float("nan")
    hf = float(np.sqrt(sse_f / n_eval)) if n_eval else float("nan")

    # -- findings --------------------------------------------------------------------------
    findings: list[Finding] = []
    if outlier.any():
        findings.append(_outlier_finding(s, glitch, base0, baseline))
    for g in accepted:
        r = rich[g] if g in fast else tests[g]
        ev = {
            "test": "Wald, block-HAC (batch means over contiguous time blocks), Holm-controlled, with a "
            + (f"slow offset wander up to degree {RICH_DEGREE} in time" if g in fast else "quadratic offset wander in time")
            + " as a nuisance",
            "F": r.f,
            "df": [r.df1, r.df2],
            "p_value": r.p,
            "alpha_familywise": alpha,
            "effect_rms_ut": r.effect_rms_ut,
            "practical_floor_ut": floor,
            "heldout_rms_ut_with": cv.get("_all"),
            "heldout_rms_ut_without": cv.get(g),
        }
        if g in wander:
            ev["block_offset_rms_ut_explained"] = float(np.sqrt(wander[g][0]))
            ev["block_offset_rms_ut_unexplained"] = float(np.sqrt(wander[g][1]))
        if g == si.EFFECT:
            findings.append(si.describe(final.soft_iron, ev))
        else:
            c = by_effect[g]
            findings.append(
                ch.describe(c, final.coef_ut_per_unit[c.channel], chans_all[c.channel], t, ev, chans_src.get(ch.TEMP))
            )

    sim = simulated_rms(final, mk, chk, noise)
    limits = _soft_iron_limits(tests[si.EFFECT], si.EFFECT in accepted, final.rms_ut, sim, float(t[-1] - t[0]))
    limits += _untested_channels(tests, by_effect)
    limits += _wander_limit(final, mk, chk, alpha, _practical_floor_ut(noise), [by_effect[g].channel for g in by_effect if g not in accepted])
    extra = {"skipped_channels": skipped, "against_rich_wander": {
            g: {"F": r.f, "p": r.p, "effect_rms_ut": r.effect_rms_ut, "accepted_as_fast": g in fast,
                "shift_inflation": inflation.get(g)} for g, r in rich.items()
        }, "survivors": list(survivors), "heldout": dict(cv), "candidates": {
            g: {"F": r.f, "p": r.p, "effect_rms_ut": r.effect_rms_ut, "coef_ut_per_unit": -r.beta if g != si.EFFECT else None}
            for g, r in tests.items()
        }}
    return Diagnosis(
        n_samples=len(series),
        baseline=baseline,
        final=final,
        findings=tuple(findings),
        baseline_heldout_rms_ut=hb,
        final_heldout_rms_ut=hf,
        simulated_rms_ut=sim,
        noise_ut=noise,
        series=s,
        outlier_mask=outlier,
        tests=extra,
        folds=tuple((int(sub[sl.start]), int(sub[sl.stop - 1]) + 1) for sl in fold_slices),
        fold_rms=tuple(fold_rms),
        limits=limits,
    )


def _untested_channels(tests: dict, by_effect: dict) -> tuple:
    """A channel term the recording could not test at all is named, with why: silence about a
    column the user logged must not read as "it has no effect"."""
    out = []
    for g, r in tests.items():
        if g == si.EFFECT or not (r.f == 0.0 and r.p >= 1.0):
            continue
        c = by_effect[g]
        what = "time" if c.channel == ch.TIME else c.channel
        if c.confounded:
            what += " (with " + ", ".join(n for n, _ in c.confounded) + ", which only rose or fell with it)"
        if r.basis.shape[1] == 0:
            why = (
                "with this motion an offset that follows it looks the same as the hard iron, a "
                "direction-dependent error or the slow wander (the sensor pointed in different "
                "directions while it changed); record while it goes up and down with the board "
                "turning through all orientations"
            )
        else:
            why = "it varies in too few independent stretches of the recording to be tested against the slow wander"
        out.append({"effect": g, "suspected": False, "channel": c.channel, "summary": f"An offset following {what} could not be tested: {why}."})
    return tuple(out)


WANDER_BLOCKS = 20


def _by_direction(r) -> str:
    if not r:
        return ""
    lo, hi = r
    return f" ({lo:.2g}–{hi:.2g} by its direction)" if hi is not None else f" ({lo:.2g} or more by its direction; along some, not at all)"


def _wander_limit(final: ModelFit, m: np.ndarray, chans: dict, alpha: float, floor_ut: float, untested: list) -> tuple:
    """Real recordings wander: the offset moves slowly in a way no logged channel explains.
    That is not a calibration term (it cannot be predicted for the next session), but it bounds
    what the calibration is good for and what slow effects this recording can identify, so it
    is stated when the final model's block offsets scatter beyond the noise (χ², at ``alpha``)
    by more than the practical floor."""
    used = {c: chans[c] for c in final.spec.channels}
    e = final.residual(m, used)
    h = final.calibration().correct(m, used)
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    rms, p = ch.offset_wander(e, u, WANDER_BLOCKS)
    if not (p < alpha and rms >= floor_ut):
        return ()
    others = [c for c in untested if c != ch.TIME]
    if others:
        tail = f"; an effect of {', '.join(others)} or of time that varies this slowly could not be told apart from it"
    elif any(c != ch.TIME for c in chans):  # every logged channel is in the model
        tail = "; a drift in time that varies this slowly could not be told apart from it"
    else:
        tail = "; a temperature (none is logged) or drift effect that varies this slowly could not be told apart from it"
    # how large a slow term of each channel not in the model would have had to be
    floors, ranges = {}, {}
    for c in untested:
        f = ch.slow_term_floor(chans[c], rms, WANDER_RATIO, WANDER_BLOCKS) if c in chans else None
        if f is not None:
            floors[c] = f
            ranges[c] = ch.slow_term_floor_range(chans[c], u, rms, WANDER_RATIO, WANDER_BLOCKS)
    if floors:
        tail += " (to be reported, a slowly varying term would have needed about " + ", ".join(
            f"{v:.2g} µT/{ch.unit_of(c)} of {'drift in time' if c == ch.TIME else c}"
            + _by_direction(ranges.get(c))
            for c, v in floors.items()
        ) + ")"
    p_text = "p < 1e-12" if p < 1e-12 else f"p = {p:.1g}"
    return (
        {
            "effect": "offset_wander",
            "suspected": True,
            "rms_ut": rms,
            "p_value": p,
            "blocks": WANDER_BLOCKS,
            "slow_term_floor_ut_per_unit": floors,
            "slow_term_floor_range_ut_per_unit": {c: list(r) for c, r in ranges.items() if r},
            "summary": (
                f"The offset wanders slowly by about {rms:.2f} µT RMS between {WANDER_BLOCKS} stretches of the recording, "
                f"more than the noise allows ({p_text}) and explained by no logged channel (environment, sensor drift, an "
                f"unlogged temperature): a calibration from this recording is good to about that much{tail}."
            ),
        },
    )


# the final model's residual this much above what it predicts for the measured noise is
# practically "something left unmodelled" (simulated clean recordings stay within ±7 %)
SUSPECT_EXCESS = 1.15


def _soft_iron_limits(test, accepted: bool, rms_ut: float, simulated_rms_ut: float, duration_s: float) -> tuple:
    """Say so when the recording could not test soft iron fully — too few directions covered,
    or too few independent stretches of motion — and whether the residual suggests it is
    there: silence must not read as "no soft iron"."""
    k = int(test.basis.shape[1])
    untested = test.p >= 1.0 and test.f == 0.0
    if k >= 5 and not untested:
        return ()
    reasons = []
    if k < 5:
        reasons.append(
            f"with this motion only {k} of the 5 soft-iron directions can be told apart from the offset, the "
            "radius and a slow wander in time, so a scale mismatch along the others would go unseen; turn the "
            "board through all orientations, visiting each more than once"
        )
    if untested and k > 0:
        reasons.append(
            f"the {duration_s:.0f} s of motion hold too few independent stretches to test it against slow "
            "wander; record longer (a few minutes), turning through all orientations more than once"
        )
    excess = rms_ut / simulated_rms_ut if simulated_rms_ut > 0 else float("nan")
    suspected = bool(np.isfinite(excess) and excess >= SUSPECT_EXCESS)
    part = "along the directions it could test, soft iron is modelled; beyond them it " if accepted else "Soft iron "
    lead = (
        part[0].upper() + part[1:] + f"is suspected but not identifiable: the residual ({rms_ut:.2f} µT) is "
        f"{excess:.2f}× what the fitted model predicts for this noise, and "
        if suspected
        else "Soft iron could not be fully tested: "
    )
    return (
        {
            "effect": si.EFFECT,
            "suspected": suspected,
            "identifiable_directions": k,
            "of_directions": 5,
            "residual_over_predicted": float(excess),
            "summary": lead + "; ".join(reasons) + ".",
        },
    )


def _outlier_finding(s: Series, glitch: gl.Glitches, base0: ModelFit, baseline: ModelFit) -> Finding:
    idx = glitch.index
    radial = np.abs(base0.residual(s.field_ut[idx], {}))
    rows = [int(v) for v in s.row[idx]]
    times = s.t_s[idx]
    seen = float(np.median(radial / np.maximum(glitch.jump_ut, 1e-9)))
    summary = (
        f"{len(idx)} sample(s) jump off the smooth trajectory by {np.median(glitch.jump_ut):.1f} µT "
        f"(median) and straight back: isolated read glitches or corrupted samples, not field. "
        + (
            f"Only about {100 * seen:.0f} % of a jump shows in |m|, so a radius check alone misses the sideways ones."
            if seen < 0.7
            else f"About {100 * min(seen, 1.0):.0f} % of a jump shows in |m|: these jumps are mostly radial."
        )
    )
    return Finding(
        effect="outliers",
        summary=summary,
        where={"time_s": [float(v) for v in times[:200]], "n": int(len(idx))},
        evidence={
            "test": "neighbour-interpolation innovation of the 3-vector (chi2(3)) and of |m - c| - r (chi2(1)), "
            "robust local scales, Bonferroni over samples and both channels",
            "threshold_z": glitch.threshold_z,
            "threshold_radial_z": glitch.threshold_radial_z if np.isfinite(glitch.threshold_radial_z) else None,
            "n_seen_in_magnitude_only": int(np.sum(glitch.radial)),
            "z": [float(v) for v in glitch.z[:200]],
            "jump_ut": [float(v) for v in glitch.jump_ut[:200]],
            "median_radial_change_ut": float(np.median(radial)),
            "median_radial_share_of_jump": seen,
        },
        params={"indices": rows},
    )


def simulated_rms(fit: ModelFit, m: np.ndarray, channels: dict, noise_ut: float, seed: int = 0) -> float:
    """RMS radial residual the fitted model itself predicts: drive the forward model
    (Calibration.distort) with the recording's own directions and channels, add white noise of
    the measured size, refit the same model and return its RMS residual."""
    cal = fit.calibration()
    used = {c: channels[c] for c in fit.spec.channels}
    h = cal.correct(m, used)
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    sim = cal.distort(u * cal.field_ut, used) + noise_ut * rng.standard_normal(m.shape)
    refit = fit_model(sim, used, fit.spec, fit.reference, start=fit)
    return float(refit.rms_ut) if refit else float("nan")
