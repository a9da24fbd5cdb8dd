"""``fit``: the one entry point — start, robust fit, outliers, ML refit, model choice, uncertainty.

    fit_calibration(m_ut_or_series, model="sphere"|"ellipsoid"|"auto", outliers=True) -> FitResult | FitFailure

1. Samples: an (n, 3) array in µT or a Series (flagged and non-finite rows are left out; they
   are neither used nor reported as outliers).
2. Start: the sphere accumulator's algebraic solution (fails on too few samples), then a
   coverage gate: the sphere's information-matrix condition must be ≤ ``max_condition``.
3. A robust ML sphere (soft-L1 loss, scale from the MAD of the start's residuals) so that
   spikes cannot drag the fit.
4. Which models can this coverage determine? For the diagonal and full ellipsoid, the
   information matrix JᵀJ at the robust sphere (unit-diagonal scaled) must have condition
   ≤ ``max_ellipsoid_condition`` (never below ``max_condition``), else the model is not
   fitted; once fitted, the 1σ of its shape terms (≈ relative gains; the z gain too, which the
   trace-free parameterisation derives from the other two) must be ≤ ``max_shape_sigma``.
   Two questions, two reasons (``Refusal``): *undetermined* — at the noise of the
   better-fitting ellipsoid, does the coverage pin the gains? (the diagonal's terms taken from
   the full model's information with its off-diagonal terms held, so they are never more open
   than the full model's own: a superset is never kept where its subset is undetermined, and
   where the diagonal is, the full one is refused too); *misfit* — judged with its own
   residuals (for the diagonal, their correlation along the recording counted,
   ``_shape_sigma``), are they still pinned? A diagonal ellipsoid on off-diagonal soft iron
   fails only the second, and the full one may then hold what it cannot. ``reason`` says which.
   The sphere has no second test, so its condition limit carries the whole judgement and is
   the tighter one; an ellipsoid's is only a backstop against a solve that cannot be trusted
   at all, and the shape-σ gate, which asks exactly what a band of directions leaves open (the
   gains), decides. A refused sphere names the offset axis its coverage leaves open and the
   turn that would determine it.
5. Each model fitted: robust fit → iterated Grubbs on its residuals (t-distribution critical
   values) → plain least squares (ML) on the kept samples → Grubbs again until nothing new.
7. Balance: "directions" refits the chosen model with weights that give each coarse
   equal-area direction cell the same total weight (``select.direction_weights``), so poses
   where the board lingered do not dominate the shape; its uncertainty is the sandwich
   covariance. "auto" (default) balances ellipsoids only: their shape is what gets
   extrapolated into sparsely visited directions, while the sphere is the exact ML estimator
   and weighting would cost it efficiency (bench/fit_crlb.py: 1.5× the CRLB with weights,
   1.0× without, on ±30° tilt trials). Nor, under "auto", an ellipsoid whose calibrated
   directions fill under ``BALANCE_MIN_COVERAGE`` of the sphere's cells: there the shape is
   extrapolated over most of the sphere, and an equal say for the few cells at the edge of
   what was seen lets their handful of samples steer it (bench/balance_foresight.py's cells:
   the fullest ellipsoid fitted on the first 30–70 % of each open recording and judged on the
   rest, the balance made the spread worse by over 1 % in 6 of the 12 cells whose first part
   covers under half of the cells and better in 2; above half, better in 14 of 37, worse in 6).
   Where the balanced fit's residuals are correlated in time beyond what independent noise
   gives (its autocorrelation factor f against the block sandwich's χ², at 1 %), a long rest in
   one pose is one visit sharing one error, not many independent looks: each run of k
   consecutive samples in a cell then weighs k/(1 + kρ) of that cell's share, with
   ρ = (f² − 1)/k̄ from the sandwich's blocks of k̄ samples (``direction_weights``), and the fit
   is redone. On independent noise nothing changes.
6. "auto": the model that predicts the recording's own held-out time blocks (``holdout``: five
   contiguous blocks, each model refitted without each block and judged there by the spread
   of |calibrated field|, on the samples whose directions the rest of the recording also
   holds). The lowest-BIC model (n·ln(mean e²) + p·ln n) stands unless another determinable
   model predicts the blocks over ``holdout.MARGIN`` better — so the model kept is never that
   much worse than the sphere on them; by BIC alone where the recording is too short for
   blocks. The same blocks, judged on all their samples, keep the direction balance of step 7
   for an ellipsoid unless the unweighted fit predicts them ``holdout.BALANCE_MARGIN`` times
   better, or better block by block beyond the blocks' scatter (judged on the blocks both
   refits reach). "ellipsoid" takes the fullest determinable
   ellipsoid and falls back (full → diagonal → sphere).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from ..core.calibration import Calibration
from ..core.series import Series
from . import geometric, holdout, uncertainty
from . import outliers as _outliers
from .coverage import coverage, side_name
from .ellipsoid import algebraic_start
from .failure import FitFailure
from .result import MODEL_NAMES, FitResult
from .direction_weights import direction_weights
from .sphere import sphere_start

MODELS = ("sphere", "ellipsoid", "auto")
BALANCE = ("auto", "directions", "none")
DEFAULT_MAX_CONDITION = 1.0e4
# the backstop: a normal matrix beyond 1e8 (a Jacobian beyond 1e4) leaves fewer than half of
# float64's digits to its solve; below it the shape-σ gate decides (at 1e5 it refused a full
# ellipsoid that gate passed on a flight log's first 70 %, whose sphere then predicted the rest
# 3× worse than the plain ellipsoid: bench/model_choice.py)
DEFAULT_MAX_ELLIPSOID_CONDITION = 1.0e8
DEFAULT_MAX_SHAPE_SIGMA = 0.01
BALANCE_MIN_COVERAGE = 0.5  # the share of coverage cells (as fit reports it) below which "auto" does not balance
_ROBUST_LOSS = "soft_l1"


def _samples(data) -> tuple[np.ndarray, np.ndarray]:
    """(m (k, 3), index (k,) into the input) of the usable rows."""
    if isinstance(data, Series):
        m, ok = data.field_ut, data.valid.copy()
    else:
        m = np.asarray(data, dtype=np.float64)
        if m.ndim != 2 or m.shape[1] != 3:
            raise ValueError(f"samples must be an (n, 3) array of µT, got shape {m.shape}")
        ok = np.ones(len(m), bool)
    ok &= np.all(np.isfinite(m), axis=1)
    idx = np.flatnonzero(ok)
    return m[idx], idx


def _fit_kind(m, kind, theta0, sigma0, use_outliers, alpha):
    """Robust → Grubbs → ML → Grubbs … for one model. Returns (GeometricFit, kept mask)."""
    sigma0 = max(min(sigma0, _outliers.robust_sigma(geometric.residual(theta0, m, kind))), 1e-9 * theta0[3])
    robust = geometric.solve(m, kind, theta0, loss=_ROBUST_LOSS, f_scale_ut=2.0 * sigma0)
    if isinstance(robust, FitFailure):
        return robust, None
    keep = np.ones(len(m), bool)
    theta = robust.theta
    resid = robust.residual_ut
    for round_ in range(4):
        if use_outliers:
            kept_idx = np.flatnonzero(keep)
            drop = kept_idx[_outliers.grubbs(resid[kept_idx], alpha=alpha)]
            if len(drop) == 0 and round_ > 0:
                break
            keep[drop] = False
        ml = geometric.solve(m[keep], kind, theta)
        if isinstance(ml, FitFailure):
            return ml, None
        theta = ml.theta
        resid = geometric.residual(theta, m, kind)
        if not use_outliers:
            break
    return ml, keep


def _gate(m, theta_sphere, kind, max_condition) -> tuple[bool, float, str]:
    """Can the coverage determine this model? Information-matrix condition at the sphere."""
    theta = np.concatenate([theta_sphere, np.zeros(geometric.N_SHAPE[kind])])
    cond = uncertainty.information_condition(geometric.jacobian(theta, m, kind))
    if cond > max_condition:
        return False, cond, (
            f"{MODEL_NAMES[kind]} not fitted: information-matrix condition {cond:.3g} > {max_condition:.3g}"
            " (coverage cannot determine it)"
        )
    return True, cond, ""


def _shape_sigma(g: geometric.GeometricFit) -> tuple[float, float]:
    """(plain, widened): the largest 1σ of the shape terms (≈ relative gains, the z gain included) from the fit's
    own residuals.

    The diagonal ellipsoid is the model left when the full one cannot be determined, and it is
    wrong whenever the soft iron has off-diagonal terms: what it cannot hold stays in its
    residuals, correlated along the recording, and on a cap of directions the offset along the
    cap's axis, the radius and the z gain trade it between them. Its gains are judged with the
    covariance that counts that correlation (the block sandwich ``fit`` reports) when that is
    the larger. (The full ellipsoid is the whole linear model; judged that way too it refused
    ellipsoids that won on real recordings.)"""
    if g.kind == "sphere":
        return 0.0, 0.0
    cov = uncertainty.covariance(g.jac, uncertainty.residual_sigma(g.residual_ut, geometric.n_params(g.kind)))
    plain = uncertainty.shape_sigma(cov)
    widened = plain
    if g.kind == "diagonal":
        block = uncertainty.block_covariance(g.jac, g.residual_ut)
        if np.all(np.isfinite(block)):
            widened = max(plain, uncertainty.shape_sigma(block))
    return plain, widened


def _bic(fit: geometric.GeometricFit) -> float:
    n = len(fit.residual_ut)
    mse = max(float(np.mean(fit.residual_ut**2)), 1e-300)
    return n * np.log(mse) + geometric.n_params(fit.kind) * np.log(n)


@dataclass(frozen=True)
class _Limits:
    outliers: bool
    alpha: float
    max_ellipsoid_condition: float
    max_shape_sigma: float
    diagonal_needed: bool = True  # False: the full ellipsoid alone is asked for, and not why (``_stands_alone``)


def fit_calibration(
    data,
    model: str = "auto",
    outliers: bool = True,
    noise_ut: float | None = None,
    alpha: float = _outliers.DEFAULT_ALPHA,
    max_condition: float = DEFAULT_MAX_CONDITION,
    max_shape_sigma: float = DEFAULT_MAX_SHAPE_SIGMA,
    balance: str = "auto",
    max_ellipsoid_condition: float = DEFAULT_MAX_ELLIPSOID_CONDITION,
    reasons: bool = True,
) -> FitResult | FitFailure:
    """Fit a calibration to magnetometer samples (µT); see the module docstring. ``reasons``:
    False where the caller reads the calibration and not why it was chosen (``fit_models``)."""
    return fit_models(data, (model,), outliers, noise_ut, alpha, max_condition, max_shape_sigma, balance,
                      max_ellipsoid_condition, reasons)[model]


def fit_models(
    data,
    models: tuple[str, ...],
    outliers: bool = True,
    noise_ut: float | None = None,
    alpha: float = _outliers.DEFAULT_ALPHA,
    max_condition: float = DEFAULT_MAX_CONDITION,
    max_shape_sigma: float = DEFAULT_MAX_SHAPE_SIGMA,
    balance: str = "auto",
    max_ellipsoid_condition: float = DEFAULT_MAX_ELLIPSOID_CONDITION,
    reasons: bool = True,
) -> dict:
    """{model: fit_calibration(data, model=model, …)} for each of ``models``, the same results,
    from one start and one fit of each candidate model (a caller that needs fit's "auto" and its
    "ellipsoid" on the same samples pays for the candidates once). ``reasons`` False: the caller
    reads the fit and not why it was chosen — for "ellipsoid" alone, the diagonal one is then not
    fitted where the full one stands without it (``_stands_alone``: the same fit is returned;
    ``reason`` and ``alternatives`` leave out what was not fitted)."""
    for model in models:
        if model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)}, not {model!r}")
    if balance not in BALANCE:
        raise ValueError(f"balance must be one of {', '.join(BALANCE)}, not {balance!r}")
    m, idx = _samples(data)
    start = _robust_sphere(m, max_condition)
    if isinstance(start, FitFailure):
        return {model: start for model in models}
    limits = _Limits(outliers, alpha, max(max_condition, max_ellipsoid_condition), max_shape_sigma,
                     reasons or set(models) != {"ellipsoid"})
    memo: dict = {}
    return {model: _result(m, idx, model, start, limits, balance, noise_ut, memo) for model in models}


def _result(m, idx, model: str, start, limits: _Limits, balance: str, noise_ut, memo: dict):
    """One model's FitResult from the shared start; ``memo`` holds the candidate fits and the
    balanced refits already made for another model on the same samples."""
    notes: list[str] = []
    candidates, conds = _candidates(m, model, *start, limits, notes, memo)
    if not candidates:
        return FitFailure("no_convergence", "; ".join(notes) or "no model could be fitted")
    chosen, balance = _choose(model, candidates, notes, m, balance)
    g, keep = candidates[chosen]
    key = ("balanced", chosen, balance)
    if key not in memo:
        said: list[str] = []
        memo[key] = (*_balanced(m[keep], g, balance, said), said)
    g, weights, said = memo[key]
    notes.extend(said)
    return FitResult(
        model=MODEL_NAMES[chosen],
        calibration=Calibration(offset_ut=g.offset_ut, field_ut=g.field_ut, soft_iron=g.soft_iron),
        summary=_Summary(g, noise_ut, weights, 0.0 if model == "sphere" else uncertainty.SPHERE_GAIN_SIGMA),
        rms_ut=g.rms_ut,
        n_used=int(keep.sum()),
        outliers=idx[~keep],
        reason="; ".join(notes),
        condition=conds[chosen],
        used=idx[keep],
        residual_ut=g.residual_ut,
        alternatives={MODEL_NAMES[k]: f.rms_ut for k, (f, _) in candidates.items()},
    )


@dataclass(frozen=True)
class _Summary:
    """A result's (uncertainty, CRLB of the offset): ``uncertainty.summarise`` of its fit, made
    when the result's uncertainty is first read (``FitResult.summary``)."""

    fit: geometric.GeometricFit
    noise_ut: float | None
    weights: np.ndarray | None
    gain_sigma: float

    def __call__(self) -> tuple[dict, np.ndarray]:
        u = uncertainty.summarise(self.fit, self.noise_ut, self.weights, self.gain_sigma)
        keys = ("offset_ut", "field_ut", "soft_iron", "autocorrelation_factor", "direction_factor", "time_block_factor")
        return {k: u[k] for k in keys}, u["crlb_offset_ut"]


def _robust_sphere(m, max_condition: float):
    """Step 2–3: the algebraic start, the robust ML sphere and its coverage gate — (the robust
    sphere, its information-matrix condition, the robust residual scale) or a failure."""
    # a permissive start (the accumulator's own gate is for live use); coverage is judged
    # below on the information matrix of the geometric fit, the same test for every model
    start = sphere_start(m, max_condition=100 * max_condition)
    if isinstance(start, FitFailure):
        return start
    e0 = np.linalg.norm(m - start[:3], axis=1) - start[3]
    sigma0 = max(_outliers.robust_sigma(e0), 1e-6 * start[3])
    robust = geometric.solve(m, "sphere", start, loss=_ROBUST_LOSS, f_scale_ut=2.0 * sigma0)
    if isinstance(robust, FitFailure):
        return robust
    sigma_r = max(_outliers.robust_sigma(robust.residual_ut), 1e-6 * robust.field_ut)
    cond_sphere = uncertainty.information_condition(robust.jac)
    if cond_sphere > max_condition:
        return FitFailure(
            "ill_conditioned",
            f"coverage too thin even for a sphere: information-matrix condition {cond_sphere:.3g}"
            f" > {max_condition:.3g}; {_motion_hint(robust)}",
        )
    return robust, cond_sphere, sigma_r


def _motion_hint(robust: geometric.GeometricFit) -> str:
    """Which motion would determine the sphere: the offset component its information matrix
    leaves open (where the centre is open, so is which side the field never came from)."""
    j = robust.jac / np.maximum(np.linalg.norm(robust.jac, axis=0), 1e-300)
    axis = np.linalg.eigh(j.T @ j)[1][:3, 0]
    name = side_name(axis).replace("+", "").replace("−", "")
    return (f"the samples leave the offset along the sensor's {name} axis open (the field's directions stay on"
            f" a band or cone about that axis): turn the board so its {name} axis also points along and against"
            " the field, e.g. roll it upside down and back")


class Refusal(Enum):
    """Why a model was left out: its coverage cannot determine it (then no superset of it can
    be trusted either), its residuals show what it cannot hold, or its solve failed."""

    UNDETERMINED = "undetermined"
    MISFIT = "misfit"
    FAILED = "failed"


def _candidates(m, model: str, robust, cond_sphere: float, sigma_r: float, limits: _Limits, notes: list,
                memo: dict | None = None):
    """Step 4–5: each model the coverage can determine, fitted — ({kind: (fit, kept mask)},
    {kind: condition}); why any was left out goes to ``notes``. Both ellipsoids are judged at
    the noise of the better-fitting one, so what decides "undetermined" is the coverage, not
    a misfit; where the diagonal one is undetermined, the full one (its superset) is too. For
    "ellipsoid" the sphere is fitted only where no ellipsoid is left (it would not be taken).
    ``memo``: the fits already made on the same samples (``fit_models``), filled here."""
    memo = {} if memo is None else memo
    conds: dict[str, float] = {"sphere": cond_sphere}
    candidates: dict[str, tuple] = {}
    if model != "sphere":
        if "ellipsoids" not in memo:
            said: list[str] = []
            memo["ellipsoids"] = (_ellipsoids(m, robust, sigma_r, limits, said), said)
        (found, e_conds), said = memo["ellipsoids"]
        conds.update(e_conds)
        notes.extend(said)
        candidates = dict(found)
    if model != "ellipsoid" or not candidates:
        if "sphere" not in memo:
            memo["sphere"] = _fit_kind(m, "sphere", robust.theta, sigma_r, limits.outliers, limits.alpha)
        sphere, keep = memo["sphere"]
        if isinstance(sphere, FitFailure):
            notes.append(f"sphere failed: {sphere.message}")
        else:
            candidates["sphere"] = (sphere, keep)
    if model == "ellipsoid":
        candidates = _fullest(candidates, notes)
    return candidates, conds


def _ellipsoids(m, robust, sigma_r: float, limits: _Limits, notes: list) -> tuple[dict, dict]:
    """The determined ellipsoids ({kind: (fit, kept mask)}, subset first) and each one's
    information-matrix condition at the robust sphere; why any was left out goes to ``notes``."""
    conds: dict[str, float] = {}
    fits: dict[str, tuple] = {}
    refused: dict[str, Refusal] = {}
    for kind in ["full", "diagonal"]:
        ok, conds[kind], why = _gate(m, robust.theta[:4], kind, limits.max_ellipsoid_condition)
        if not ok:
            notes.append(why)
            refused[kind] = Refusal.UNDETERMINED
            continue
        if kind == "diagonal" and not limits.diagonal_needed and _stands_alone(fits.get("full"), limits.max_shape_sigma):
            return {"full": fits["full"]}, conds
        f, keep = _fit_kind(m, kind, _start_of(m, kind, robust, notes), sigma_r, limits.outliers, limits.alpha)
        if isinstance(f, FitFailure):
            notes.append(f"{MODEL_NAMES[kind]} failed: {f.message}")
            refused[kind] = Refusal.FAILED
            continue
        fits[kind] = (f, keep)
    return _determined(fits, refused, limits.max_shape_sigma, notes), conds


def _determined(fits: dict, refused: dict, limit: float, notes: list) -> dict:
    """The fitted ellipsoids that pass the shape-σ gate, subset first ({kind: (fit, keep)})."""
    noise_ut = min(uncertainty.residual_sigma(f.residual_ut, geometric.n_params(f.kind)) for f, _ in fits.values()) \
        if fits else 0.0
    out: dict[str, tuple] = {}
    for kind in ("diagonal", "full"):
        if kind not in fits:
            continue
        if kind == "full" and refused.get("diagonal") is Refusal.UNDETERMINED:
            notes.append(f"{MODEL_NAMES[kind]} rejected: its subset, the diagonal ellipsoid, is already undetermined")
            continue
        # the diagonal's terms as the full model's information holds them (its off-diagonal terms
        # known): never more open than the full model's own, so a superset cannot pass where
        # its subset is undetermined
        jac = fits["full"][0].jac[:, : geometric.n_params(kind)] if "full" in fits else fits[kind][0].jac
        verdict = _shape_verdict(fits[kind][0], jac, noise_ut, limit)
        if verdict is None:
            out[kind] = fits[kind]
        else:
            refused[kind], why = verdict
            notes.append(f"{MODEL_NAMES[kind]} rejected: {why} (limit {100 * limit:.2g} %)")
    return out


def _stands_alone(full, limit: float) -> bool:
    """Whether the full ellipsoid (``(fit, kept mask)`` or None) passes ``_determined``'s gate
    whatever the diagonal one's fit holds, once the diagonal's coverage has passed ``_gate``:
    the diagonal's fit enters that gate only through the shared noise, the smaller of the two
    fits' — so through the two coverage checks, whose σ grows with the noise. Both pass at the
    full fit's own noise with a margin no rounding crosses, and its own residuals pin its gains."""
    if full is None:
        return False
    f = full[0]
    noise_ut = uncertainty.residual_sigma(f.residual_ut, geometric.n_params("full"))
    for kind in ("diagonal", "full"):
        cov = uncertainty.covariance(f.jac[:, : geometric.n_params(kind)], noise_ut)
        if not uncertainty.shape_sigma(cov) <= limit * (1.0 - 1e-9):
            return False
    return max(_shape_sigma(f)) <= limit


def _shape_verdict(f: geometric.GeometricFit, jac: np.ndarray, noise_ut: float, limit: float):
    """None where the model's gains are pinned to ``limit``; else (Refusal, why). Undetermined:
    the coverage (``jac``, at the shared noise level) leaves them open. Misfit: the model's own
    residuals (and, for the diagonal, their correlation along the recording) leave them open —
    what it cannot hold, which a fuller model may."""
    pinned = uncertainty.shape_sigma(uncertainty.covariance(jac, noise_ut))
    if pinned > limit:
        return Refusal.UNDETERMINED, f"the coverage determines its gains only to ±{100 * pinned:.2g} %"
    plain, widened = _shape_sigma(f)
    if max(plain, widened) > limit:
        return Refusal.MISFIT, (
            f"its own residuals, which hold what its shape cannot, leave its gains open to ±{100 * max(plain, widened):.2g} %"
            f" (±{100 * pinned:.2g} % from the coverage alone)"
        )
    return None


def _fullest(candidates: dict, notes: list) -> dict:
    """``model="ellipsoid"``: the fullest model left (full → diagonal → sphere)."""
    for kind in ("full", "diagonal", "sphere"):
        if kind in candidates:
            if kind == "sphere":
                notes.append("fell back to the sphere")
            return {kind: candidates[kind]}
    return {}


def _start_of(m, kind: str, robust, notes: list) -> np.ndarray:
    """Where a model's fit starts: the robust sphere, or the algebraic ellipsoid when it exists."""
    if kind == "sphere":
        return robust.theta
    alg = algebraic_start(m, kind)
    if isinstance(alg, FitFailure):
        notes.append(f"algebraic start rejected ({alg.reason}); started from the sphere")
        return np.concatenate([robust.theta[:4], np.zeros(geometric.N_SHAPE[kind])])
    return alg


def _choose(model: str, candidates: dict, notes: list, m, balance: str) -> tuple[str, str]:
    """Step 6: the model reported — for "auto", the one that best predicts held-out time blocks
    of the recording (by BIC where it is too short to cut into blocks) — and why; with the
    balance to give it ("auto" balance: an ellipsoid is balanced unless its held-out blocks
    say the plain fit predicts better)."""
    if model == "auto" and len(candidates) > 1:
        held = holdout.judge(m, candidates)
        if held is None:
            return _by_bic(candidates, notes), balance
        chosen = _by_holdout(held, _by_bic(candidates, []), notes)
        if balance == "auto" and chosen != "sphere" and not held.balanced[chosen]:
            notes.append("no direction balance: unweighted, it predicts the held-out blocks better")
            balance = "none"
        return chosen, balance
    return _only(model, candidates, notes), balance


def _only(model: str, candidates: dict, notes: list) -> str:
    chosen = next(iter(candidates))
    if model == "sphere":
        notes.append("sphere requested")
    elif model == "ellipsoid" and chosen != "sphere":
        notes.append(f"{MODEL_NAMES[chosen]} is the fullest model the coverage determines")
    elif model == "auto":
        notes.append(f"{MODEL_NAMES[chosen]} is the only model the coverage determines")
    return chosen


def _by_holdout(held: holdout.HeldOutSpread, default: str, notes: list) -> str:
    """The model the held-out blocks choose over ``default`` (the lowest BIC), and why."""
    chosen = held.choose(default)
    others = ", ".join(f"{MODEL_NAMES[k]} {100 * v:.3g} %" for k, v in held.spread.items() if k != chosen)
    pct = f"{100 * holdout.MARGIN:.2g} %"
    if chosen == default:
        verdict = f"has the lowest BIC, and no model predicts the recording's held-out time blocks {pct} better"
    else:
        verdict = f"predicts the recording's held-out time blocks over {pct} better than {MODEL_NAMES[default]} (lowest BIC)"
    notes.append(
        f"{MODEL_NAMES[chosen]} {verdict}: |field| spread {100 * held.spread[chosen]:.3g} % (refitted without"
        f" each of {held.n_blocks} blocks; {others})"
    )
    if held.unseen_blocks:
        which = ", ".join(str(j + 1) for j in held.unseen_blocks)
        notes.append(f"time block {which} of {held.n_blocks} holds directions the rest of the recording"
                     " hardly shows: judged only where the rest saw them")
    return chosen


def _by_bic(candidates: dict, notes: list) -> str:
    bics = {k: _bic(f) for k, (f, _) in candidates.items()}
    chosen = min(bics, key=bics.get)
    others = ", ".join(f"{MODEL_NAMES[k]} {bics[k] - bics[chosen]:+.1f}" for k in bics if k != chosen)
    notes.append(f"{MODEL_NAMES[chosen]} has the lowest BIC (ΔBIC: {others}; too few samples for held-out blocks)")
    return chosen


def _balanced(mk, g, balance: str, notes: list):
    """Step 7: the chosen fit refitted with equal weight per direction cell when asked (or, for
    "auto", for an ellipsoid), then, where its residuals are correlated in time, with each
    visit to a cell weighted as one shared error — (the fit, its weights or None)."""
    if not (balance == "directions" or (balance == "auto" and g.kind != "sphere")):
        return g, None
    seen = coverage((mk - g.offset_ut) @ g.soft_iron.T) if balance == "auto" else 1.0
    if seen < BALANCE_MIN_COVERAGE:
        notes.append(f"no direction balance: {100 * seen:.0f} % of directions seen, under"
                     f" {100 * BALANCE_MIN_COVERAGE:.0f} %; an equal say for the few cells at the edge of"
                     " what was seen would steer the shape across the directions never seen")
        return g, None
    g, weights = _reweighted(mk, g, None, 0.0)
    if weights is None:
        return g, None
    notes.append("samples weighted so each direction cell counts equally")
    f = uncertainty.autocorrelation_factor(g, weights)
    if uncertainty.beyond_independent_noise(f, len(mk)):
        gv, wv = _reweighted(mk, g, weights, uncertainty.shared_error_ratio(f, len(mk)))
        if wv is not weights:
            g, weights = gv, wv
            notes.append("residuals correlated in time: each visit to a direction cell weighted as one shared error")
    return g, weights


def _reweighted(mk, g, weights, rho: float):
    """Two passes of: direction weights from the current fit's calibrated samples, refit."""
    for _ in range(2):
        w = direction_weights((mk - g.offset_ut) @ g.soft_iron.T, visit_correlation=rho)
        gw = geometric.solve(mk, g.kind, g.theta, weights=w)
        if isinstance(gw, FitFailure):
            break
        g, weights = gw, w
    return g, weights
