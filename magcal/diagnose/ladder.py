"""The diagnosis ladder: fit, test, select, refit, compare, describe — as a short pipeline.

``diagnose(series)`` runs these steps, each a function below with its own docstring:

1. ``prepare`` — valid, finite samples in time order;
2. ``set_aside_glitches`` — glitches found from the smoothness of the 3-vector trajectory
   (magcal.diagnose.glitches) and set aside; a long recording analysed on a subsample;
3. ``fit_baseline`` — hard iron + radius (the sphere);
4. ``test_terms`` — every candidate term at the baseline (magcal.diagnose.design): soft iron and
   one offset-versus-channel term per channel and for time, block-HAC Wald tests with the
   direction harmonics and a quadratic offset wander as nuisances, and each channel again
   against a rich wander, calibrated by its own circular shifts;
5. ``select_terms`` — Holm, the practical floor, the wander gate and the held-out gain
   (magcal.diagnose.selection);
6. ``refit`` — the accepted terms fitted jointly (nonlinear least squares on the radial
   residual);
7. ``compare_heldout`` — baseline and final model on contiguous held-out time blocks;
8. ``compare_with_simulation`` — the fitted model, driven with the recording's own
   directions, timing and channels plus the measured noise, predicts the residual RMS a correct
   model would leave (the place where a richer simulation of the sensor plugs in);
9. ``describe`` — findings and limits in words and figures.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..core.errors import InputError
from ..core.series import Series
from . import channels, design, glitches, limits, selection, softiron
from .diagnosis import Diagnosis
from .finding import Finding
from .inference import contiguous_blocks
from .model import FitFailure, ModelFit, Spec, fit_model

ALPHA = 0.01
FOLDS = 5
MIN_SAMPLES = 50
MAX_ANALYSED = 200_000


@dataclass(frozen=True)
class Analysed:
    """The samples the ladder works on: a time-ordered (sub)sample with glitches flagged."""

    series: Series  # every valid, finite sample, time-ordered
    rows: np.ndarray  # which of them are analysed (all, or a systematic subsample)
    glitches: glitches.Glitches
    outlier: np.ndarray  # (len(series),) flagged as a glitch
    m: np.ndarray  # analysed field, µT
    t: np.ndarray  # analysed times, s
    keep: np.ndarray  # analysed and not a glitch
    chans: dict  # analysed channel arrays, time included as channels.TIME

    @property
    def logged(self) -> dict:
        """The logged channels (without time)."""
        return {c: v for c, v in self.chans.items() if c != channels.TIME}

    @property
    def kept(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """(field, times, channels) of the analysed samples that are not glitches."""
        return self.m[self.keep], self.t[self.keep], {c: v[self.keep] for c, v in self.chans.items()}


@dataclass(frozen=True)
class Selected:
    """What survived each stage of selection, for the findings and the JSON's ``tests``."""

    tests: dict  # effect → WaldResult against the quadratic wander
    rich: design.RichTests
    fast: set
    survivors: list
    wander: dict  # effect → (explained, unexplained) block-offset mean squares
    accepted: list
    heldout: dict
    skipped: list  # channels that could not be candidates (constant, missing values)
    candidates: dict  # channel effect → ChannelCandidate


STEPS = ("set_aside_glitches", "fit_baseline", "select_terms", "refit", "compare_heldout",
         "compare_with_simulation", "describe")


def diagnose(series: Series, alpha: float = ALPHA, folds: int = FOLDS, on_step=None) -> Diagnosis:
    """Model discovery on one recording (see the module docstring for the ladder).
    ``on_step(name)``, when given, is told as each step begins (``STEPS``: a progress display)."""
    step = on_step or (lambda name: None)
    step("set_aside_glitches")
    analysed = set_aside_glitches(prepare(series), alpha)
    step("fit_baseline")
    baseline, base_kept = fit_baseline(analysed)
    noise_ut = analysed.glitches.noise_ut
    step("select_terms")
    selected = select_terms(analysed, base_kept, alpha, noise_ut, folds)
    step("refit")
    final, accepted = refit(analysed, base_kept, selected)
    selected = replace(selected, accepted=accepted)
    fold_slices = contiguous_blocks(len(analysed.m), folds)
    step("compare_heldout")
    heldout_b, heldout_f, fold_rms = compare_heldout(analysed, baseline, final, fold_slices)
    m_kept, _, chans_kept = analysed.kept
    step("compare_with_simulation")
    simulated = compare_with_simulation(final, m_kept, chans_kept, noise_ut)
    step("describe")
    findings = describe_findings(analysed, selected, final, base_kept, alpha, noise_ut)
    return Diagnosis(
        n_samples=len(series),
        baseline=baseline,
        final=final,
        findings=findings,
        baseline_heldout_rms_ut=heldout_b,
        final_heldout_rms_ut=heldout_f,
        simulated_rms_ut=simulated,
        noise_ut=noise_ut,
        series=analysed.series,
        outlier_mask=analysed.outlier,
        tests=tests_record(selected),
        folds=tuple((int(analysed.rows[sl.start]), int(analysed.rows[sl.stop - 1]) + 1) for sl in fold_slices),
        fold_rms=tuple(fold_rms),
        limits=describe_limits(analysed, selected, final, simulated, alpha, noise_ut),
    )


def prepare(series: Series) -> Series:
    """Valid, finite samples in time order; too few is an InputError."""
    s = series.only_valid()
    ok = np.all(np.isfinite(s.field_ut), axis=1) & np.isfinite(s.t_s)
    if not ok.all():
        s = s.take(ok)
    if len(s) and np.any(np.diff(s.t_s) < 0):
        s = s.take(np.argsort(s.t_s, kind="stable"))
    if len(s) < MIN_SAMPLES:
        raise InputError(f"diagnosis needs at least {MIN_SAMPLES} valid samples, the recording has {len(s)}")
    return s


def set_aside_glitches(s: Series, alpha: float) -> Analysed:
    """Glitches are searched in every sample; a long recording is then analysed on a
    systematic (time-ordered) subsample: MAX_ANALYSED samples already pin every parameter far
    below the noise."""
    n = len(s)
    found = glitches.detect(s.field_ut, s.t_s, alpha=alpha)
    outlier = np.zeros(n, bool)
    outlier[found.index] = True
    rows = np.arange(n) if n <= MAX_ANALYSED else np.linspace(0, n - 1, MAX_ANALYSED).round().astype(np.int64)
    chans = {c: v[rows] for c, v in s.channels.items()}
    chans[channels.TIME] = s.t_s[rows]
    return Analysed(s, rows, found, outlier, s.field_ut[rows], s.t_s[rows], ~outlier[rows], chans)


def _require(fit, what: str) -> ModelFit:
    if isinstance(fit, FitFailure):
        raise InputError(f"cannot fit the {what}: {fit.message}")
    return fit


def fit_baseline(a: Analysed) -> tuple[ModelFit, ModelFit]:
    """The sphere on every analysed sample (the reported baseline) and on those kept."""
    baseline = _require(fit_model(a.m, {}, Spec()), "sphere")
    m_kept, _, _ = a.kept
    return baseline, _require(fit_model(m_kept, {}, Spec(), start=baseline), "sphere")


def test_terms(a: Analysed, base: ModelFit, alpha: float) -> tuple[design.Design, dict, design.RichTests, list]:
    """Build the candidate design at the baseline and test every term (magcal.diagnose.design).
    Returns the design, the tests against the quadratic wander, the rich-wander tests of the
    channels and the channels skipped as constant or incomplete."""
    m_kept, t_kept, chans_kept = a.kept
    candidates, skipped = channels.candidates(a.t, a.logged)
    dsg = design.build(m_kept, t_kept, chans_kept, base, candidates)
    tests = design.block_wald(dsg.x, dsg.residual_ut, dsg.groups)
    rich = design.test_against_rich_wander(dsg, m_kept, t_kept, chans_kept, alpha)
    return dsg, tests, rich, skipped


def select_terms(a: Analysed, base: ModelFit, alpha: float, noise_ut: float, folds: int) -> Selected:
    """Which tested terms earn a place (magcal.diagnose.selection): significant, above the
    practical floor, past the wander gate, and helping the held-out residual."""
    dsg, tests, rich, skipped = test_terms(a, base, alpha)
    floor_ut = selection.practical_floor_ut(noise_ut)
    verdict = selection.significant(tests, rich.results, alpha, floor_ut)
    survivors = selection.above_floor(tests, verdict, floor_ut)
    _, _, chans_kept = a.kept
    survivors, wander = selection.wander_gate(dsg, chans_kept, survivors, verdict.fast)
    accepted, heldout = selection.drop_by_heldout(dsg, survivors, folds)
    return Selected(tests, rich, verdict.fast, survivors, wander, accepted, heldout, skipped, dsg.candidates)


def refit(a: Analysed, base: ModelFit, selected: Selected) -> tuple[ModelFit, list]:
    """The accepted terms fitted jointly on the kept samples; on failure the baseline (never a
    half-built model). Soft iron is restricted to the directions its test could identify."""
    accepted = selected.accepted
    cands = selected.candidates
    soft_dirs = None
    if softiron.EFFECT in accepted and selected.tests[softiron.EFFECT].basis.shape[1] < 5:
        soft_dirs = tuple(map(tuple, selected.tests[softiron.EFFECT].basis))
    spec = Spec(
        soft_iron=softiron.EFFECT in accepted,
        channels=tuple(cands[g].channel for g in accepted if g != softiron.EFFECT),
        soft_dirs=soft_dirs,
    )
    reference = {cands[g].channel: cands[g].reference for g in accepted if g != softiron.EFFECT}
    m_kept, _, chans_kept = a.kept
    final = fit_model(m_kept, chans_kept, spec, reference, start=base)
    if isinstance(final, FitFailure):
        return base, []
    return final, list(accepted)


def compare_heldout(a: Analysed, baseline: ModelFit, final: ModelFit, fold_slices: list) -> tuple[float, float, list]:
    """Baseline and final model refitted without each contiguous time block and judged on it
    (glitches excluded): (baseline held-out RMS, final held-out RMS, (baseline, final) per block)."""
    sse_b = sse_f = 0.0
    n_eval = 0
    fold_rms = []
    for held in fold_slices:
        train = np.ones(len(a.m), bool)
        train[held] = False
        test = ~train & a.keep
        fit_b = fit_model(a.m[train], {}, Spec(), start=baseline)
        train_k = train & a.keep
        fit_f = fit_model(a.m[train_k], {c: v[train_k] for c, v in a.chans.items()}, final.spec, final.reference, start=final)
        if not fit_b or not fit_f or not test.any():
            continue
        res_b = fit_b.residual(a.m[test], {})
        res_f = fit_f.residual(a.m[test], {c: v[test] for c, v in a.chans.items()})
        sse_b += res_b @ res_b
        sse_f += res_f @ res_f
        n_eval += int(test.sum())
        fold_rms.append((float(np.sqrt(np.mean(res_b**2))), float(np.sqrt(np.mean(res_f**2)))))
    if not n_eval:
        return float("nan"), float("nan"), fold_rms
    return float(np.sqrt(sse_b / n_eval)), float(np.sqrt(sse_f / n_eval)), fold_rms


def compare_with_simulation(fit: ModelFit, m: np.ndarray, chans: dict, noise_ut: float, seed: int = 0) -> float:
    """RMS radial residual the fitted model itself predicts: drive the forward model
    (Calibration.distort) with the recording's own directions and channels, add white noise of
    the measured size, refit the same model and return its RMS residual."""
    cal = fit.calibration()
    used = {c: chans[c] for c in fit.spec.channels}
    h = cal.correct(m, used)
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    sim = cal.distort(u * cal.field_ut, used) + noise_ut * rng.standard_normal(m.shape)
    refit_sim = fit_model(sim, used, fit.spec, fit.reference, start=fit)
    return float(refit_sim.rms_ut) if refit_sim else float("nan")


simulated_rms = compare_with_simulation


def _evidence(g: str, selected: Selected, alpha: float, floor_ut: float) -> dict:
    """The statistics behind one accepted term (a finding's ``evidence``)."""
    fast = g in selected.fast
    r = selected.rich.results[g] if fast else selected.tests[g]
    nuisance = f"slow offset wander up to degree {design.RICH_DEGREE} in time" if fast else "quadratic offset wander in time"
    ev = {
        "test": "Wald, block-HAC (batch means over contiguous time blocks), Holm-controlled, with a "
        + nuisance
        + " as a nuisance",
        "F": r.f,
        "df": [r.df1, r.df2],
        "p_value": r.p,
        "alpha_familywise": alpha,
        "effect_rms_ut": r.effect_rms_ut,
        "practical_floor_ut": floor_ut,
        "heldout_rms_ut_with": selected.heldout.get("_all"),
        "heldout_rms_ut_without": selected.heldout.get(g),
    }
    if g in selected.wander:
        ev["block_offset_rms_ut_explained"] = float(np.sqrt(selected.wander[g][0]))
        ev["block_offset_rms_ut_unexplained"] = float(np.sqrt(selected.wander[g][1]))
    return ev


def describe_findings(a: Analysed, selected: Selected, final: ModelFit, base: ModelFit, alpha: float, noise_ut: float) -> tuple:
    """The findings: glitches (if any), then each accepted term with its evidence."""
    out: list[Finding] = []
    if a.outlier.any():
        idx = a.glitches.index
        radial = base.residual(a.series.field_ut[idx], {})
        out.append(glitches.describe(a.glitches, a.series.row[idx], a.series.t_s[idx], radial))
    floor_ut = selection.practical_floor_ut(noise_ut)
    for g in selected.accepted:
        ev = _evidence(g, selected, alpha, floor_ut)
        if g == softiron.EFFECT:
            out.append(softiron.describe(final.soft_iron, ev))
            continue
        cand = selected.candidates[g]
        coef = final.coef_ut_per_unit[cand.channel]
        out.append(channels.describe(cand, coef, a.chans[cand.channel], a.t, ev, a.chans.get(channels.TEMP)))
    return tuple(out)


def describe_limits(a: Analysed, selected: Selected, final: ModelFit, simulated: float, alpha: float, noise_ut: float) -> tuple:
    """What the recording could not test: soft iron, untestable channels, the offset wander."""
    m_kept, _, chans_kept = a.kept
    duration_s = float(a.t[-1] - a.t[0])
    found_soft = softiron.EFFECT in selected.accepted
    out = limits.soft_iron_limits(selected.tests[softiron.EFFECT], found_soft, final.rms_ut, simulated, duration_s)
    out += limits.untested_channels(selected.tests, selected.candidates)
    left_out = [selected.candidates[g].channel for g in selected.candidates if g not in selected.accepted]
    floor_ut = selection.practical_floor_ut(noise_ut)
    return out + limits.wander_limit(final, m_kept, chans_kept, alpha, floor_ut, left_out)


def tests_record(selected: Selected) -> dict:
    """The intermediate statistics (``Diagnosis.tests``; not part of the JSON)."""
    rich = {
        g: {"F": r.f, "p": r.p, "effect_rms_ut": r.effect_rms_ut, "accepted_as_fast": g in selected.fast,
            "shift_inflation": selected.rich.inflation.get(g)}
        for g, r in selected.rich.results.items()
    }
    candidates = {
        g: {"F": r.f, "p": r.p, "effect_rms_ut": r.effect_rms_ut, "coef_ut_per_unit": -r.beta if g != softiron.EFFECT else None}
        for g, r in selected.tests.items()
    }
    return {"skipped_channels": selected.skipped, "against_rich_wander": rich, "survivors": list(selected.survivors),
            "heldout": dict(selected.heldout), "candidates": candidates}
