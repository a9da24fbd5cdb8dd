"""The diagnosis ladder: fit, test, select, refit, compare, describe — as a short pipeline.

``diagnose(series)`` runs these steps, each a function below with its own docstring:

1. ``prepare`` — valid, finite samples in time order;
2. ``set_aside_glitches`` — glitches found from the smoothness of the 3-vector trajectory
   (magcal.diagnose.glitches) and set aside; a long recording analysed on a subsample;
3. ``fit_baseline`` — hard iron + radius (the sphere);
   ``screen_channels`` — channels that follow the orientation or the reading left out
   (magcal.diagnose.hygiene);
   ``fit_reference`` — the sphere plus soft iron along every direction the data determine,
   fitted with the logged channels' offsets taken out;
4. ``test_terms`` — every candidate term at the baseline (magcal.diagnose.design): soft iron and
   one offset-versus-channel term per channel and for time, block-HAC Wald tests with the
   direction harmonics and a quadratic offset wander as nuisances, and each channel again
   against a rich wander; every test judged against draws of the recording's own twin
   (magcal.diagnose.null: the false-alarm rate set on data that wander as the recording does);
5. ``select_terms`` — Holm, the practical floor, the wander gate and the held-out gain
   (magcal.diagnose.selection);
6. ``refit`` — the accepted terms fitted jointly (nonlinear least squares on the radial
   residual);
7. ``compare_heldout`` — baseline and final model on contiguous held-out time blocks, the
   calibration returned never worse than fit's (magcal.diagnose.heldout);
8. ``compare_with_simulation`` — the fitted model, driven with the recording's own
   directions, timing and channels plus the measured noise, predicts the residual RMS a correct
   model would leave (the place where a richer simulation of the sensor plugs in);
9. ``describe`` — findings and limits in words and figures.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..core.errors import DataInsufficient
from ..core.series import Series
from . import channels, claims, collinear, design, glitches, hygiene, locate, longrun, null, selection, softiron, statements, timewords
from .locate import faults
from .locate import step as locate_step
from .heldout import choose_calibration
from .diagnosis import Diagnosis
from .inference import contiguous_blocks, n_test_blocks
from .wander_jump import jump_limit
from .model import FitFailure, ModelFit, Spec, fit_model, fit_with_channel_terms

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

    screened: tuple = ()  # data faults set aside before the fit (magcal.diagnose.locate, kind FAULT)

    @property
    def logged(self) -> dict:
        """The logged channels (without time)."""
        return {c: v for c, v in self.chans.items() if c != channels.TIME}

    @property
    def logged_kept(self) -> dict:
        """The logged channels (without time) of the samples that are not glitches."""
        return {c: v for c, v in self.kept[2].items() if c != channels.TIME}

    @cached_property
    def kept(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """(field, times, channels) of the analysed samples that are not glitches. Taken once
        (every step asks for them; a diagnosis took the same copies nine times) and read-only:
        the steps share them."""
        m, t, chans = self.m[self.keep], self.t[self.keep], {c: v[self.keep] for c, v in self.chans.items()}
        for v in (m, t, *chans.values()):
            v.flags.writeable = False
        return m, t, chans


@dataclass(frozen=True)
class Selected:
    """What survived each stage of selection, for the findings and the JSON's ``tests``."""

    tests: dict  # effect → WaldResult against the quadratic wander, judged against the twin
    rich: dict  # channel effect → WaldResult against the rich wander, judged against the twin
    fast: set
    survivors: list
    wander: dict  # effect → (explained, unexplained) block-offset mean squares
    accepted: list
    heldout: dict
    skipped: list  # channels that could not be candidates (constant, missing values)
    candidates: dict  # channel effect → ChannelCandidate
    design: design.Design  # the columns every channel was tested with
    n_tests: int  # hypotheses in Holm's family
    null: null.NullDraws  # the twin's draws every test was judged against
    wander_nuisance: bool = True  # the quadratic offset wander was a nuisance of ``tests`` (the residual shows a wander)
    pair: collinear.PairChoice | None = None  # soft iron and time, when neither passed beside the other (collinear.resolve)


STEPS = ("set_aside_glitches", "fit_baseline", "select_terms", "refit", "compare_heldout", "locate",
         "compare_with_simulation", "describe")


@timewords.in_recording_time
def diagnose(series: Series, alpha: float = ALPHA, folds: int = FOLDS, screen: bool = True, on_step=None,
             twin_null: bool = True) -> Diagnosis:
    """Model discovery on one recording (see the module docstring for the ladder).
    ``screen``: leave out channels that follow the orientation or the reading
    (magcal.diagnose.hygiene); False when the user named the channels. ``on_step(name)``, when
    given, is told as each step begins (``STEPS``: a progress display). ``twin_null``: judge
    every test against the recording's twin (magcal.diagnose.null); False refers them to the F
    distribution alone, white noise as the null (to measure what the twin changes)."""
    step = on_step or (lambda name: None)
    step("set_aside_glitches")
    prepared, screened = prepare(series)
    analysed = replace(set_aside_glitches(prepared, alpha), screened=screened)
    step("fit_baseline")
    baseline, base_kept = fit_baseline(analysed)
    analysed, left_out = screen_channels(analysed, base_kept) if screen else (analysed, ())
    reference, at_channels = fit_reference(analysed, base_kept)
    noise_ut = analysed.glitches.noise_ut
    step("select_terms")
    selected = select_terms(analysed, reference, alpha, noise_ut, folds, twin_null, at_channels)
    step("refit")
    final, selected, refused = refit_claims(analysed, reference, selected)
    fold_slices = contiguous_blocks(len(analysed.m), folds)
    step("compare_heldout")
    channel_cov = {selected.candidates[g].channel: statements.estimating_test(g, selected).cov
                   for g in selected.accepted if g in selected.candidates}
    chosen = choose_calibration(analysed, baseline, final, fold_slices, channel_cov)
    m_kept, t_kept, chans_kept = analysed.kept
    step("locate")
    found = locate_step.locate_and_model(m_kept, t_kept, analysed.logged_kept, chosen.model, chosen.fit_model,
                                         noise_ut, locate.EFFECTS, chosen.known, series.clock)
    found = replace(found, found=analysed.screened + found.found)
    step("compare_with_simulation")
    simulated = compare_with_simulation(final, m_kept, chans_kept, noise_ut)
    step("describe")
    wander = statements.measure_wander(full_model(analysed, reference, final) if found.model is None else found.model,
                                       m_kept if found.model is None else found.cleaned_ut, chans_kept, t_kept, alpha)
    floors = statements.channel_floors(selected, wander, chans_kept, alpha, noise_ut)
    return Diagnosis(
        n_samples=len(series),
        baseline=baseline,
        final=found.model or chosen.model,
        findings=locate.one_per_channel(statements.findings(analysed, selected, final, base_kept, alpha, noise_ut),
                                        locate.as_findings(found.found, found.verdicts)),
        baseline_heldout_rms_ut=chosen.heldout.rms_ut[0],
        final_heldout_rms_ut=chosen.heldout_rms_ut if found.model is None else found.heldout_rms_ut,
        simulated_rms_ut=simulated,
        noise_ut=noise_ut,
        series=analysed.series,
        outlier_mask=analysed.outlier,
        tests=statements.tests_record(selected),
        folds=tuple((int(analysed.rows[sl.start]), int(analysed.rows[sl.stop - 1]) + 1) for sl in fold_slices),
        fold_rms=chosen.fold_rms,
        fit_heldout_rms_ut=chosen.fit_heldout_rms_ut,
        diagnosis_model=final,
        calibration_from=chosen.source, calibration_located=found.model is not None,
        located=found,
        limits=statements.left_out(left_out) + tuple(r.limit() for r in refused)
        + locate.as_limits(found.found, found.verdicts)
        + statements.limits(analysed, selected, final, simulated, wander, alpha=alpha,
                            located=locate.said(found.found, found.verdicts))
        + jump_limit(wander.jump, found.floor_ut, found.found)
        + chosen.limits,
        floors={c: f.to_dict() for c, f in floors.items()},
    )


def prepare(series: Series) -> tuple[Series, tuple]:
    """Valid, finite samples with data faults set aside (magcal.diagnose.locate.faults: stuck
    axes, rails, swapped axes, bad timestamps, screened in acquisition order), then in time
    order; too few is DataInsufficient (an InputError). Returns the samples and the faults found."""
    s = series.only_valid()
    ok = np.all(np.isfinite(s.field_ut), axis=1) & np.isfinite(s.t_s)
    if not ok.all():
        s = s.take(ok)
    screen = faults.screen(s.t_s, s.field_ut) if len(s) >= MIN_SAMPLES else None
    if screen is not None and screen.n_set_aside:
        s = s.take(screen.keep)
    if len(s) and np.any(np.diff(s.t_s) < 0):
        s = s.take(np.argsort(s.t_s, kind="stable"))
    if len(s) < MIN_SAMPLES:
        raise DataInsufficient(f"diagnosis needs at least {MIN_SAMPLES} valid samples, the recording has {len(s)}")
    return s, (screen.found if screen is not None else ())


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
        raise DataInsufficient(f"cannot fit the {what}: {fit.message}")
    return fit


def fit_baseline(a: Analysed) -> tuple[ModelFit, ModelFit]:
    """The sphere on every analysed sample (the reported baseline) and on those kept."""
    baseline = _require(fit_model(a.m, {}, Spec()), "sphere")
    m_kept, _, _ = a.kept
    return baseline, _require(fit_model(m_kept, {}, Spec(), start=baseline), "sphere")


def screen_channels(a: Analysed, base: ModelFit) -> tuple[Analysed, tuple]:
    """Leave out the channels that follow the board's orientation or the magnetic reading
    itself (magcal.diagnose.hygiene), judged on the directions about the baseline offset."""
    if not a.logged:
        return a, ()
    d = a.m - base.offset_ut
    kept, left = hygiene.screen(a.logged, d / np.linalg.norm(d, axis=1, keepdims=True), a.t)
    if not left:
        return a, ()
    chans = dict(kept)
    chans[channels.TIME] = a.chans[channels.TIME]
    return replace(a, chans=chans), left


def fit_reference(a: Analysed, base: ModelFit) -> tuple[ModelFit, dict]:
    """The model every term is tested at: hard iron, radius and soft iron along every direction
    the data determine (softiron.determined_directions), fitted on the kept samples with the
    logged channels' offsets taken out (``without_channel_offsets``); the sphere when the
    motion determines none or the ellipsoid cannot be fitted. With it, the logged channels'
    offset coefficients (µT per unit) fitted beside a full soft iron (``with_channel_offsets``): the
    point, with the reference, where the candidate design is linearised (design.build)."""
    m_kept, sphere = without_channel_offsets(a, base)
    dirs = softiron.determined_directions(m_kept, sphere.offset_ut, sphere.rms_ut)
    if dirs.shape[1] == 0:
        return base, {}
    spec = Spec(soft_iron=True, soft_dirs=None if dirs.shape[1] == 5 else tuple(map(tuple, dirs)))
    ref = fit_model(m_kept, {}, spec, start=sphere)
    if isinstance(ref, FitFailure):
        return base, {}
    return with_channel_offsets(a, ref, sphere)


def with_channel_offsets(a: Analysed, ref: ModelFit, sphere: ModelFit) -> tuple[ModelFit, dict]:
    """The reference, and the logged channels' offsets fitted on the kept samples beside hard
    iron, radius and soft iron along all five directions, from the reference: (the reference,
    channel → µT per unit). The sphere's own estimates of those offsets carry whatever a sphere
    leaves of the soft iron that follows the motion (a real HMC5883L's 2.4 µT sphere misfit
    made a 0.15 µT/A current 1.2 µT/A there); fitted beside the reference's soft iron alone
    (the directions the data determine), they still take up the soft iron along the others: on
    a twin of the tomisuarez noisy take (two directions determined, gains 0.68–1.50) it leaves
    1.1 µT of misfit with no noise at all, and that fit handed a null channel and a current,
    neither in the draw, (−2.9, 0.0, −2.7) and (2.9, −0.4, 0.7) µT per unit. The reference as
    it is, with no offsets, when there are no logged channels or the joint fit fails."""
    if not sphere.spec.channels:
        return ref, {}
    m_kept, _, chans = a.kept
    spec = replace(ref.spec, channels=sphere.spec.channels, soft_dirs=None)
    joint = fit_model(m_kept, chans, spec, sphere.reference, start=ref)
    if isinstance(joint, FitFailure):
        return ref, {}
    return ref, joint.coef_ut_per_unit


def without_channel_offsets(a: Analysed, base: ModelFit) -> tuple[np.ndarray, ModelFit]:
    """The kept samples with every logged candidate channel's offset taken out, as the sphere
    fitted with all of them estimates it, and that sphere. An offset that follows a channel and
    is left in drags a soft-iron fit along the offset–gain valley (a 3.7 µT intermittent current
    on a ±40° partial sphere: a reference with 36 % of soft iron and a 100 µT radius, and the
    soft-iron test, linearised there, missed a 1.5 % soft iron and found one where there was
    none). Where the sphere misfits (soft iron), its estimates take up part of the misfit too
    (a 0.15 µT/A current read as 1.2 µT/A on a twin of a real HMC5883L recording):
    ``with_channel_offsets`` fits them again beside the reference. Time is not among them: on
    a single sweep time follows the direction, and a drift fitted beside the sphere takes up
    the soft iron itself. The sphere as it was when no logged channel can be fitted."""
    m_kept, _, chans = a.kept
    cands = [c for c in channels.candidates(a.t, a.logged)[0] if c.channel != channels.TIME]
    if not cands:
        return m_kept, base
    spec = Spec(channels=tuple(c.channel for c in cands))
    fit = fit_model(m_kept, chans, spec, {c.channel: c.reference for c in cands}, start=base)
    if isinstance(fit, FitFailure):
        return m_kept, base
    return m_kept - fit.calibration().channel_offset_ut(chans, len(m_kept)), fit


def test_terms(a: Analysed, ref: ModelFit, twin_null: bool = True, at_channels: dict | None = None
               ) -> tuple[design.Design, dict, dict, list, null.NullDraws, bool]:
    """Build the candidate design at the reference model and test every term
    (magcal.diagnose.design): soft iron along the directions the data determine, every channel
    with soft iron in place (so that the soft iron a sphere leaves cannot pass for a channel),
    each test judged against the recording's twin (magcal.diagnose.null). Returns the design,
    the tests against the quadratic wander (a nuisance only where the residual shows a wander,
    ``wander_seen``), the rich-wander tests of the channels, the channels skipped as constant or
    incomplete, the twin's draws, and whether the quadratic wander was a nuisance. ``at_channels``:
    the channel coefficients the design is linearised at (fit_reference)."""
    m_kept, t_kept, chans_kept = a.kept
    candidates, skipped = channels.candidates(a.t, a.logged)
    dsg = design.build(m_kept, t_kept, chans_kept, ref, candidates, at_channels)
    draws = draw_null(a, dsg) if twin_null else null.none(len(m_kept), "the twin as the null was switched off")
    e_null = (draws.e, draws.white) if draws.count else None
    seen = draws.count > 0 or wander_seen(dsg, t_kept)
    tests = tested_columns(dsg, seen, e_null).test(dsg.groups)
    rich = design.test_against_rich_wander(dsg, t_kept, e_null)
    return dsg, tests, rich, skipped, draws, seen


def tested_columns(dsg: design.Design, seen: bool, e_null: tuple | None) -> collinear.Tested:
    """What every test runs on: the design's columns, with the quadratic wander only where the
    residual shows a wander (``seen``: free, the quadratic wander takes most of a 1.3-cycle
    temperature swing on a band of directions even where the residual shows no wander at all,
    see wander_seen), each group's coverage gate (its effect's, design.Design.coverage_gates) and
    the twin's draws ``e_null``."""
    return collinear.Tested(dsg.x if seen else dsg.x[:, : dsg.n_before_wander], dsg.residual_ut, dsg.groups,
                            dsg.coverage_gates, e_null)


def wander_seen(dsg: design.Design, t: np.ndarray) -> bool:
    """Whether the residual with every candidate fitted (design.Design.x_candidates: every
    column but the wander nuisance, and soft iron along the directions the tests leave out)
    shows a slow wander: its block sums are not those of white noise (null.white_p, as for the twin), or an offset
    following the Legendre polynomials of degree 2 (the nuisance's own) and above in time is
    significant beside every candidate term (longrun.shows_wander); either at
    null.WHITE_LEVEL. Only then is the quadratic wander a nuisance of the tests: as free
    columns it takes most of a 1.3-cycle temperature swing on a band of directions (there the
    offset the temperature moves lies nearly along the band's axis, where a slow offset and a
    slow gain look alike) even where the residual shows no wander at all — on simulated bands
    without wander a temperature's noncentrality of 40–93 fell to 2–21 with it."""
    x, q = dsg.x_candidates, dsg.basis_of_candidates
    residual = dsg.residual_ut - q @ (q.T @ dsg.residual_ut)
    if null.white_p(residual, contiguous_blocks(len(residual), n_test_blocks(len(residual)))) <= null.WHITE_LEVEL:
        return True
    return longrun.shows_wander(x, dsg.residual_ut, t, dsg.offset_directions, design.WANDER_DEGREE, q)


def draw_null(a: Analysed, dsg: design.Design) -> null.NullDraws:
    """The recording's twin, learned from the residual with every candidate fitted
    (design.Design.x_candidates: every column of the design but the wander, and soft iron along
    the directions the tests leave out), around the full candidate model, and its draws with no
    candidate term (magcal.diagnose.null), each with the residual's part along those left-out
    directions added (design.misfit_left): fixed by the recording's geometry, it is in every
    test's residual, so a channel that lines up with it does so in the draws alike (added to the
    draws, not to their wander-free copies; nothing is added where the motion determines all
    five directions)."""
    m_kept, t_kept, chans_kept = a.kept
    q = dsg.basis_of_candidates

    def project(v):
        return v - q @ (q.T @ v)

    residual = project(dsg.residual_ut)
    p_white = null.white_p(residual, contiguous_blocks(len(residual), n_test_blocks(len(residual))))
    if p_white > null.WHITE_LEVEL:
        return null.none(len(m_kept), f"the residual is consistent with white noise (p = {p_white:.2g} for its "
                                      "block sums): the F distribution is its null")
    try:
        model = null.learn(residual, project, m_kept, t_kept, dsg.directions, design.full_candidate_calibration(dsg))
    except (ValueError, np.linalg.LinAlgError) as exc:
        return null.none(len(m_kept), f"no twin could be learned ({exc})")
    drawn = null.draws(model, dsg.directions, t_kept, chans_kept)
    return replace(drawn, e=drawn.e + design.misfit_left(dsg)[:, None])


def select_terms(a: Analysed, ref: ModelFit, alpha: float, noise_ut: float, folds: int, twin_null: bool = True,
                 at_channels: dict | None = None) -> Selected:
    """Which tested terms earn a place (magcal.diagnose.selection): significant, above the
    practical floor, past the wander gate, and helping the held-out residual."""
    dsg, tests, rich, skipped, draws, seen = test_terms(a, ref, twin_null, at_channels)
    floor_ut = selection.practical_floor_ut(noise_ut)
    verdict = selection.significant(tests, rich, alpha, floor_ut)
    e_null = (draws.e, draws.white) if draws.count else None
    tests, pair = collinear.resolve(tested_columns(dsg, seen, e_null), tests, verdict.rejected, alpha)
    extra = pair.family_entry() if pair is not None else {}
    if extra:
        verdict = selection.significant(tests, rich, alpha, floor_ut, extra)
    soft_size = softiron.fitted_size(dsg.x[:, dsg.groups[softiron.EFFECT]], dsg.soft_dirs, ref)
    survivors = selection.above_floor(tests, verdict, floor_ut, soft_size)
    _, _, chans_kept = a.kept
    survivors, wander = selection.wander_gate(dsg, chans_kept, survivors, verdict.fast)
    accepted, heldout = selection.drop_by_heldout(dsg, survivors, folds)
    n_tests = len(selection.family(tests, rich, extra))
    return Selected(tests, rich, verdict.fast, survivors, wander, accepted, heldout, skipped, dsg.candidates, dsg, n_tests,
                    draws, seen, pair)


def refit(a: Analysed, ref: ModelFit, selected: Selected) -> tuple[ModelFit, list]:
    """The accepted terms fitted on the kept samples; on failure the reference (never a
    half-built model). Soft iron, when found, is carried along every direction the data
    determine (the reference's), not only along those its test could tell from the nuisances.
    A channel coefficient is the one its test estimated with the wander nuisance in place (a
    plain refit would hand it part of the wander); offset, soft iron and radius are refitted
    around it."""
    accepted = selected.accepted
    cands = selected.candidates
    with_soft = softiron.EFFECT in accepted and ref.spec.soft_iron
    spec = Spec(
        soft_iron=with_soft,
        channels=tuple(cands[g].channel for g in accepted if g in cands),
        soft_dirs=ref.spec.soft_dirs if with_soft else None,
    )
    reference = {cands[g].channel: cands[g].reference for g in accepted if g in cands}
    m_kept, _, chans_kept = a.kept
    coefs = {cands[g].channel: -statements.estimating_test(g, selected).beta for g in accepted if g in cands}
    final = fit_with_channel_terms(m_kept, chans_kept, spec, reference, coefs, start=ref)
    if isinstance(final, FitFailure):
        return ref, [softiron.EFFECT] if ref.spec.soft_iron else []
    return final, list(accepted)


def refit_claims(a: Analysed, ref: ModelFit, selected: Selected) -> tuple[ModelFit, Selected, tuple]:
    """``refit``, then the claims check (magcal.diagnose.claims): a term whose halves in time
    disagree, or whose size is implausible, is dropped and the rest refitted without it."""
    final, accepted = refit(a, ref, selected)
    selected = replace(selected, accepted=accepted)
    m_kept, t_kept, chans_kept = a.kept
    kept, refused = claims.screen(m_kept, t_kept, chans_kept, final, accepted, selected.candidates)
    if not refused:
        return final, selected, ()
    gone = tuple(r.group for r in refused)
    regated, shares = selection.wander_gate(selected.design, chans_kept, kept, selected.fast, left_out=gone)
    selected = replace(selected, wander={**selected.wander, **shares})
    final, accepted = refit(a, ref, claims.without(selected, regated))
    return final, replace(selected, accepted=accepted), refused


def full_model(a: Analysed, ref: ModelFit, final: ModelFit) -> ModelFit:
    """The final model with every soft-iron direction the data determine, whether or not soft
    iron was reported: the wander and the floors are stated with the full calibration in
    place (a soft iron left out would otherwise pass for wander and inflate both)."""
    if final.spec.soft_iron or not ref.spec.soft_iron:
        return final
    m_kept, _, chans_kept = a.kept
    spec = Spec(soft_iron=True, channels=final.spec.channels, soft_dirs=ref.spec.soft_dirs)
    full = fit_with_channel_terms(m_kept, chans_kept, spec, final.reference, final.coef_ut_per_unit, start=ref)
    return final if isinstance(full, FitFailure) else full


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
