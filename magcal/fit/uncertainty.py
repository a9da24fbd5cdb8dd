"""Uncertainty of a geometric fit: the parameter covariance from the Jacobian, its translation
to 1σ of offset, radius and soft-iron matrix, the Cramér–Rao bound for the data's own geometry,
and the information-matrix conditioning that decides which model the coverage can support.

For residuals e = (|W(m − b)| − r)/‖W û‖ (``geometric``: the radial error in the raw samples' µT)
with independent Gaussian noise of σ per sample, the Fisher
information is JᵀJ/σ², so Cov(θ) ≥ σ²(JᵀJ)⁻¹ (the CRLB), which the ML fit attains to first order.
Reported covariance uses σ̂² = Σe²/(n − p); the CRLB uses a given noise σ (or σ̂ when none).

Real recordings are not independent samples: the motion is smooth and slow unmodelled terms
(the offset wandering by tenths of a µT over a minute) make neighbouring residuals alike, and
the independent-noise covariance is then optimistic. Samples are in time order, so the
reported covariance is the larger of that and a batch-means (block) sandwich that sums the
score over contiguous time blocks and so keeps any correlation shorter than a block; the ratio
is reported as ``autocorrelation_factor`` (≈ 1 on independent noise).

Neither sees how much the answer depends on *which directions* the recording saw. Where the
model is not quite the sensor (a gain that moves with temperature, a field that varies with
position, a small nonlinearity), a part of the recording that saw other directions gives
another calibration, by more than either σ says: on the real recordings the halves' offsets
and gains differed by 2–3 times the block-sandwich σ, at every time scale (quarters as much as
halves), while the scatter between time blocks within a fit matched it. So each σ is also
widened by how far a delete-a-group jackknife over six direction groups — the six faces of a
cube about the sensor, by the dominant axis of each sample's direction and its sign, the six
orientations of the classic calibration — linearised at the fit (no refits), moves the answer
beyond what that same jackknife gives on independent noise (which is ≈ 1 on clean data: the
faces' unequal leverage alone is not counted as doubt). The widening is reported as
``direction_factor`` (the largest over the offset; ≥ 1).

A sphere that ``fit --model auto`` chose states its axis gains equal by assumption, not by
measurement, and its offset and field are what they are only if that holds: on a band of
directions an unmodelled gain moves the centre along the band's axis by many µT (the halves of a
flight log, one mostly on the ground, chose a sphere and an ellipsoid and differed by 11 µT in
z against a stated 0.4). So where the model was chosen, not asked for, the sphere's covariance
adds what axis gains spread as real sensors' are would do to it (``gain_doubt``): the shape terms
of the full ellipsoid taken as unknown with an isotropic prior of ``SPHERE_GAIN_SIGMA`` per
log-gain (the same for any labelling of the axes), pushed through the offset and field they
trade with, G P Gᵀ with G = A_bb⁻¹ A_bs at the sphere; and its soft-iron σ is that prior's,
not 0. On a full sphere of directions G ≈ 0 and only the soft-iron σ changes.

Each of those σ is itself estimated, from few independent pieces where it matters: the six faces
of the jackknife (five degrees of freedom), the sandwich's 12–40 time blocks. A 95 % interval
from a σ estimated with ν degrees of freedom is Student's t_ν wide, not the normal's 1.96 (2.57
for the jackknife's five), so each σ is stated multiplied by t_ν(97.5 %)/1.96
(``few_dof_factor``): ±1.96 σ is then the 95 % interval it claims to be.

None of those asks how much the answer depends on *which stretch of time* the recording holds.
The sandwich's short blocks see correlation shorter than a block, the faces see which directions
were seen, but a recording is also a sequence: the offset wanders over minutes, the tilts that pin
a flight's ellipsoid come in one stretch, a hand turn covers one face early and another late.
Cut in two, such a recording gives halves further apart than any of those σ: on the open real
recordings the misses were where the halves saw other shares of the six faces (a flight log's
halves 62 % apart in their face shares, a 324-sample hand turn's 30 %, an RM3100 hand turn's
21 % where the faces' jackknife had widened nothing). So each σ is also at least what a delete-a-block jackknife
over ``TIME_BLOCKS`` contiguous time blocks says: the spread of the answers the fit gives,
made again, with each eighth of the recording missing (refitted, not linearised as the faces'
jackknife is: on a cap of directions one eighth moved a sphere's centre ten times a
Gauss–Newton step's estimate, and the linearised σ left the halves' change uncovered).
It carries wander, correlation longer than the sandwich's blocks and coverage that arrives in
one stretch, all at once; where the rest of the recording hardly pins a parameter without one
block, it says so by a wide σ. Its variance has K − 1 = 7 degrees of freedom, so it is stated
with t₇'s 95 % point; the larger of it and the analytic σ above is kept per parameter
(``time_block_factor``: the largest widening of the offset's σ; ≥ 1).
"""

from __future__ import annotations

import numpy as np

from . import geometric
from .failure import FitFailure
from .tails import chi2_isf, t_isf

# 1σ of a sensor's log axis gain about the mean of its three (trace-free; each axis's 95 % interval
# ±1.96·√(2/3)·σ). Real sensors' spread is heavy-tailed: of the 11 open devices whose whole
# recordings pin a full ellipsoid, most are within ±0.03, the HMC5883L and the GearVR reach 0.106
# and 0.108, the QMC5883L 0.40 (0.049 as σ without it, 0.13 with it); the LSM303DLHC datasheet's
# z gain (980 against 1100 LSB/gauss) is 0.077. This σ is the smallest whose interval (±0.112)
# holds every axis but the QMC5883L's two (31 of 33; notebook § The sphere's gain prior)
SPHERE_GAIN_SIGMA = 0.07
# contiguous time blocks of the delete-a-block jackknife (module docstring): long enough to
# carry a stretch's own directions and wander, enough of them for a variance (7 degrees of freedom)
TIME_BLOCKS = 8
Z95 = 1.959963984540054  # the two-sided 95 % point of the normal distribution


def covariance(jac: np.ndarray, sigma_ut: float) -> np.ndarray:
    """σ²(JᵀJ)⁻¹ (pseudo-inverse when singular)."""
    JtJ = jac.T @ jac
    return sigma_ut**2 * np.linalg.pinv(JtJ, rcond=1e-15, hermitian=True)


def residual_sigma(residual_ut: np.ndarray, n_params: int) -> float:
    e = np.asarray(residual_ut)
    return float(np.sqrt(e @ e / max(len(e) - n_params, 1)))


def soft_iron_sigma(theta: np.ndarray, kind: str, cov: np.ndarray) -> np.ndarray:
    """1σ of each entry of W (3×3) by first-order propagation of the shape parameters."""
    if kind == "sphere":
        return np.zeros((3, 3))
    _, dWs = geometric.expm_derivatives(kind, theta[4:])
    G = np.column_stack([dW.reshape(9) for dW in dWs])  # 9 × k
    C = G @ cov[4:, 4:] @ G.T
    return np.sqrt(np.clip(np.diag(C), 0.0, None)).reshape(3, 3)


def weighted_covariance(jac: np.ndarray, weights: np.ndarray, sigma_ut: float) -> np.ndarray:
    """Sandwich covariance of a weighted least-squares estimate under iid noise σ:
    σ² (JᵀWJ)⁻¹ (JᵀW²J) (JᵀWJ)⁻¹."""
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    A = np.linalg.pinv(jac.T @ (w[:, None] * jac), rcond=1e-15, hermitian=True)
    B = jac.T @ ((w * w)[:, None] * jac)
    return sigma_ut**2 * A @ B @ A


def block_count(n: int, requested: int | None = None) -> int:
    """How many contiguous time blocks the batch-means sandwich cuts n samples into: as
    requested or √n/2 within 12…40, at least 4 samples a block (1 below 8 samples: no sandwich)."""
    b = int(requested or np.clip(np.sqrt(n) / 2.0, 12, 40))
    return max(min(b, n // 4), 2) if n >= 8 else 1


def block_covariance(jac: np.ndarray, residual_ut: np.ndarray, weights=None, n_blocks: int | None = None) -> np.ndarray:
    """Batch-means sandwich A (Σ_b g_b g_bᵀ) A · B/(B − 1), A = (JᵀWJ)⁻¹, g_b = J_bᵀW_b e_b over
    B contiguous blocks of the (time-ordered) samples: robust to residuals correlated over
    less than a block. B = √n/2 within 12…40 (enough blocks for a usable variance estimate)."""
    n = len(residual_ut)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    b = block_count(n, n_blocks)
    A = np.linalg.pinv(jac.T @ (w[:, None] * jac), rcond=1e-15, hermitian=True)
    if b < 2:
        return np.full_like(A, np.nan)
    edges = np.linspace(0, n, b + 1).round().astype(int)[:-1]
    g = np.add.reduceat(jac * (w * np.asarray(residual_ut))[:, None], edges, axis=0)
    g -= g.mean(axis=0)  # the scores sum to zero at the optimum; remove rounding
    return A @ (g.T @ g) @ A * (b / (b - 1.0))


def _covariances(fit: geometric.GeometricFit, s_hat: float, weights=None):
    """(independent-noise covariance, block sandwich, their offset-trace ratio's square root)."""
    cov_iid = covariance(fit.jac, s_hat) if weights is None else weighted_covariance(fit.jac, weights, s_hat)
    cov_blk = block_covariance(fit.jac, fit.residual_ut, weights)
    t_iid = float(np.trace(cov_iid[:3, :3]))
    t_blk = float(np.trace(cov_blk[:3, :3])) if np.all(np.isfinite(cov_blk)) else 0.0
    factor = float(np.sqrt(t_blk / t_iid)) if t_iid > 0 and t_blk > 0 else 1.0
    return cov_iid, cov_blk, factor


def autocorrelation_factor(fit: geometric.GeometricFit, weights=None) -> float:
    """How much wider the offset's 1σ is when residuals correlated in time are counted
    (block sandwich over independent noise), at least 1: ≈ 1 on independent noise."""
    s_hat = residual_sigma(fit.residual_ut, geometric.n_params(fit.kind))
    return max(_covariances(fit, s_hat, weights)[2], 1.0)


def beyond_independent_noise(factor: float, n: int) -> bool:
    """Is an autocorrelation factor beyond what independent noise gives, at 1 %? Over the
    sandwich's B blocks its variance is the independent figure times a χ² with B − 1 degrees of
    freedom over B − 1, compared with that χ²'s 99th percentile."""
    k = block_count(n) - 1
    if k < 2:
        return False
    return factor * factor > float(chi2_isf(0.01, k)) / k


def shared_error_ratio(factor: float, n: int) -> float:
    """ρ, the error a sample shares with its neighbours relative to its own noise, from the
    offset's autocorrelation factor f: over the sandwich's blocks of k̄ samples the variance
    grows by f² = 1 + k̄ρ, so ρ = (f² − 1)/k̄ (0 on independent noise)."""
    return (factor * factor - 1.0) * block_count(n) / n


def direction_groups(jac: np.ndarray) -> np.ndarray:
    """Per sample, which of the six faces (0…5: −x, +x, −y, +y, −z, +z) its direction is nearest,
    the direction read from the offset columns of the Jacobian (∂e/∂b = −Wᵀû)."""
    u = -np.asarray(jac)[:, :3]
    axis = np.argmax(np.abs(u), axis=1)
    return axis * 2 + (u[np.arange(len(u)), axis] > 0)


def direction_ratio(jac: np.ndarray, residual_ut: np.ndarray, weights=None, faces_out: list | None = None) -> np.ndarray | None:
    """Per parameter, the delete-a-group jackknife's variance over the six direction groups
    divided by what that jackknife gives on independent noise alone, at least 1 (the excess
    counted wherever it is positive, as a variance component's estimate is — a χ²(K − 1) test
    deciding whether to count it left the intervals short exactly where the excess is real but
    modest); None where fewer than three groups can be left out.

    Linearised: leaving group k out moves θ by (A − A_k)⁻¹ J_kᵀW_k e_k (A = JᵀWJ), and the
    jackknife is (K − 1)/K Σ of the moves' outer products about their mean. With independent
    noise of variance s² per unit weight a move has covariance s²(A − A_k)⁻¹A_k(A − A_k)⁻¹, so
    the jackknife's expectation is (K − 1)²/K² Σ_k of those — larger than the fit's own σ since
    faces differ in leverage; dividing by it leaves ≈ 1 on clean data and the excess where the
    faces disagree. A group is left out only where it holds at least as many samples as
    parameters and at most a third of them (leaving out most of a cap recording measures the
    cap's geometry, not the model), and the rest still pins the parameters. ``faces_out``, when
    given, receives the number of faces left out in turn (the jackknife's K)."""
    faces = _leave_a_face_out(jac, residual_ut, weights)
    if faces is None:
        return None
    moves, a_out, a, s2 = faces
    k = len(moves)
    if faces_out is not None:
        faces_out.append(k)
    inv = np.linalg.inv(a_out)
    null = s2 * (k - 1.0) ** 2 / k**2 * np.einsum("kij,kjl,klm->im", inv, a - a_out, inv)
    ratio = _jackknife_variance(moves) / np.clip(np.diag(null), 1e-300, None)
    return np.maximum(ratio, 1.0)


def direction_jackknife_variance(jac: np.ndarray, residual_ut: np.ndarray, weights=None) -> np.ndarray | None:
    """Per parameter, the delete-a-group jackknife's variance over the six direction groups as
    it is (its leverage share included: a floor, not an estimate); None as ``direction_ratio``."""
    faces = _leave_a_face_out(jac, residual_ut, weights)
    return None if faces is None else _jackknife_variance(faces[0])


def _jackknife_variance(moves: np.ndarray) -> np.ndarray:
    d = moves - moves.mean(axis=0)
    return np.sum(d * d, axis=0) * (len(d) - 1.0) / len(d)


def _leave_a_face_out(jac, residual_ut, weights):
    """(moves (K, p), A − A_k (K, p, p), A, s² per unit weight) over the faces that can be left out."""
    e = np.asarray(residual_ut, np.float64)
    n, p = jac.shape
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    groups = direction_groups(jac)
    order = np.argsort(groups, kind="stable")
    edges = np.searchsorted(groups[order], np.arange(7))
    js, wjs, es = jac[order], (w[:, None] * jac)[order], e[order]
    kept = [k for k in range(6) if p <= edges[k + 1] - edges[k] <= n / 3]  # a face that is most of the data is no perturbation
    if len(kept) < 3:
        return None
    a = js.T @ wjs
    a_out = np.stack([a - js[edges[k]:edges[k + 1]].T @ wjs[edges[k]:edges[k + 1]] for k in kept])
    g = np.stack([wjs[edges[k]:edges[k + 1]].T @ es[edges[k]:edges[k + 1]] for k in kept])
    pinned = conditions(a_out) <= 1e12
    if pinned.sum() < 3:
        return None
    a_out, g = a_out[pinned], g[pinned]
    moves = np.linalg.solve(a_out, g[..., None])[..., 0]
    return moves, a_out, a, float(np.sum(w * e * e)) / max(n - p, 1)


def conditions(jtjs: np.ndarray) -> np.ndarray:
    """Condition numbers of a stack of normal matrices, each scaled to unit diagonal."""
    d = np.sqrt(np.clip(np.einsum("kii->ki", jtjs), 1e-300, None))
    ev = np.linalg.eigvalsh(jtjs / (d[:, :, None] * d[:, None, :]))
    return np.where(ev[:, 0] > 0, ev[:, -1] / np.maximum(ev[:, 0], 1e-300), np.inf)


def information_condition_of(jtj: np.ndarray) -> float:
    """Condition number of a normal matrix scaled to unit diagonal (inf where singular)."""
    d = np.sqrt(np.diag(jtj))
    if np.any(d <= 0) or not np.all(np.isfinite(d)):
        return float("inf")
    r = jtj / np.outer(d, d)
    ev = np.linalg.eigvalsh(0.5 * (r + r.T))
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def _widened_by_directions(cov: np.ndarray, fit: geometric.GeometricFit, weights) -> tuple[np.ndarray, float, np.ndarray]:
    """(cov with each parameter's σ multiplied by the square root of its direction ratio where
    that is above 1, correlations kept; the largest widening of the offset's σ; per parameter,
    the degrees of freedom of the jackknife where it set the σ, else inf)."""
    faces: list = []
    ratio = direction_ratio(fit.jac, fit.residual_ut, weights, faces)
    if ratio is None:
        return cov, 1.0, np.full(len(cov), np.inf)
    r = np.sqrt(np.maximum(ratio, 1.0))
    dof = np.where(r > 1.0, faces[0] - 1.0, np.inf)
    return cov * np.outer(r, r), float(np.max(r[:3])), dof


def time_block_covariance(fit: geometric.GeometricFit, weights=None,
                          n_blocks: int = TIME_BLOCKS) -> tuple[np.ndarray, int] | None:
    """(the delete-a-block jackknife's covariance of θ over ``n_blocks`` contiguous blocks of the
    time-ordered samples, the number of blocks it used); None where there are too few samples
    for at least three blocks of as many samples as parameters.

    Each block's move is the refit's: the fit made again from θ without the block, θ₋ₖ − θ. A
    move linearised at the fit, (A − A_k)⁻¹ J_kᵀW_k e_k (A = JᵀWJ), is one Gauss–Newton step and
    holds where the objective is quadratic over the move; on a cap of directions the centre trades
    with the radius far from quadratically, and there the step fell short many times (a phone's
    half, leaving out one eighth, moved its z offset 37 µT; the step said 4). Where a refit does
    not converge the linearised move stands in — the pseudo-inverse's, large where the rest does
    not pin θ without the block: the answer rests on that stretch."""
    e = np.asarray(fit.residual_ut, np.float64)
    jac = fit.jac
    n, p = jac.shape
    k = min(int(n_blocks), n // max(p, 1))
    if k < 3:
        return None
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    wj = w[:, None] * jac
    edges = np.linspace(0, n, k + 1).round().astype(int)
    a = jac.T @ wj
    samples = fit.at[1].T
    moves = np.empty((k, p))
    for b, (i, j) in enumerate(zip(edges[:-1], edges[1:])):
        keep = np.r_[0:i, j:n]
        refit = geometric.solve(samples[keep], fit.kind, fit.theta, weights=None if weights is None else w[keep])
        if isinstance(refit, FitFailure):  # the linearised move stands in
            moves[b] = np.linalg.pinv(a - jac[i:j].T @ wj[i:j], rcond=1e-15, hermitian=True) @ (wj[i:j].T @ e[i:j])
        else:
            moves[b] = refit.theta - fit.theta
    d = moves - moves.mean(axis=0)
    return d.T @ d * (k - 1.0) / k, k


def _widened_by_time_blocks(cov: np.ndarray, fit: geometric.GeometricFit, weights) -> tuple[np.ndarray, float]:
    """(cov with each parameter's σ raised to the time-block jackknife's, stated for Student's t
    with its K − 1 degrees of freedom, where that is larger — correlations kept; the largest
    widening of the offset's σ)."""
    jack = time_block_covariance(fit, weights)
    if jack is None:
        return cov, 1.0
    t = float(few_dof_factor(np.array([jack[1] - 1.0]))[0])
    var = np.clip(np.diag(cov), 1e-300, None)
    r = np.sqrt(np.maximum(np.diag(jack[0]) * t * t / var, 1.0))
    return cov * np.outer(r, r), float(np.max(r[:3]))


def few_dof_factor(dof: np.ndarray) -> np.ndarray:
    """Per parameter, t_ν(97.5 %) / 1.96: how much wider a 95 % interval is when its σ was
    estimated from ν independent pieces (Student's t) than when σ is known; 1 for ν = inf."""
    dof = np.asarray(dof, np.float64)
    out = np.ones(len(dof))
    finite = np.isfinite(dof) & (dof > 0)
    if finite.any():
        out[finite] = t_isf(0.025, dof[finite]) / Z95
    return np.maximum(out, 1.0)


def gain_prior(gain_sigma: float) -> np.ndarray:
    """Covariance of the full ellipsoid's five shape terms (s_xx, s_yy, s_xy, s_xz, s_yz) under an
    isotropic prior on the symmetric log-gain matrix — each diagonal entry of variance σ², each
    off-diagonal σ²/2 — with its trace (the common gain, which is the field's) taken out."""
    v = gain_sigma * gain_sigma
    p = np.zeros((5, 5))
    p[:2, :2] = v * np.array([[2.0, -1.0], [-1.0, 2.0]]) / 3.0
    p[2:, 2:] = np.eye(3) * v / 2.0
    return p


def gain_doubt(theta: np.ndarray, m: np.ndarray, residual_ut: np.ndarray, gain_sigma: float,
               noise_var: float) -> tuple[np.ndarray, np.ndarray]:
    """(the 4×4 mean square error a sphere's offset and field (θ, fitted to the samples ``m`` with
    residuals ``residual_ut``) carry from axis gains it takes as equal, G E[s sᵀ] Gᵀ with
    G = A_bb⁻¹ A_bs; the soft-iron root mean square error (3×3) of its W = I). E[s sᵀ] is the
    full ellipsoid's shape terms' posterior second moment: ``gain_prior`` updated by what the
    samples say of them at ``noise_var`` per sample (nothing on a band of directions, much on a
    full sphere) — the spread left plus the gains the samples lean to."""
    full_theta = np.concatenate([np.asarray(theta, np.float64)[:4], np.zeros(geometric.N_SHAPE["full"])])
    jac = geometric.jacobian(full_theta, m, "full")
    a, grad = jac.T @ jac, jac.T @ np.asarray(residual_ut, np.float64)
    g = np.linalg.lstsq(a[:4, :4], a[:4, 4:], rcond=None)[0]
    schur = (a[4:, 4:] - a[4:, :4] @ g) / noise_var
    post = np.linalg.inv(np.linalg.inv(gain_prior(gain_sigma)) + schur)
    lean = -post @ (grad[4:] - g.T @ grad[:4]) / noise_var
    second = post + np.outer(lean, lean)
    cov = np.zeros((9, 9))
    cov[4:, 4:] = second
    return g @ second @ g.T, soft_iron_sigma(full_theta, "full", cov)


def gain_widening(theta, m: np.ndarray, info: np.ndarray, noise_var: float, widen: np.ndarray) -> np.ndarray:
    """The tracker's per-axis widening of its sphere's offset σ (``info``: its weighted normal
    matrix; σ² = noise_var · info⁻¹) grown by what axis gains the sphere takes as equal would do
    to the offset (``gain_doubt``: the sphere is in force because memory did not yet pin an
    ellipsoid, so its gains are assumed, not measured)."""
    try:
        var = np.diag(np.linalg.inv(info))[:3] * noise_var
    except np.linalg.LinAlgError:
        return widen
    e = geometric.residual(theta, m, "sphere")
    extra = np.diag(gain_doubt(theta, m, e, SPHERE_GAIN_SIGMA, noise_var)[0])[:3]
    return np.sqrt(widen**2 + np.clip(extra, 0.0, None) / np.clip(var, 1e-300, None))


def _sphere_samples(fit: geometric.GeometricFit) -> np.ndarray:
    """The samples a sphere fit was made on, from the fit itself: m = b − ∂e/∂b · (r + e)."""
    return fit.theta[:3] - fit.jac[:, :3] * (fit.theta[3] + fit.residual_ut)[:, None]


def summarise(fit: geometric.GeometricFit, noise_ut: float | None = None, weights=None,
              gain_sigma: float = 0.0) -> dict:
    """{'offset_ut': [3], 'field_ut': σ, 'soft_iron': [[3×3]]} (1σ) and the CRLB of the offset
    (the bound of any unbiased estimator for this data's geometry — the weighted fit's own
    covariance sits at or above it). ``gain_sigma`` > 0 on a sphere: its axis gains are in doubt
    (a model chosen, not asked for; ``gain_doubt``), reported as ``gain_doubt_factor`` (the
    largest widening of the offset's σ)."""
    s_hat = residual_sigma(fit.residual_ut, geometric.n_params(fit.kind))
    cov_iid, cov_blk, factor = _covariances(fit, s_hat, weights)
    cov, by_directions, dof = _widened_by_directions(cov_blk if factor > 1.0 else cov_iid, fit, weights)
    if factor > 1.0:
        dof = np.minimum(dof, block_count(len(fit.residual_ut)) - 1.0)
    t = few_dof_factor(dof)
    cov, by_time = _widened_by_time_blocks(cov * np.outer(t, t), fit, weights)
    crlb = covariance(fit.jac, s_hat if noise_ut is None else float(noise_ut))
    soft = soft_iron_sigma(fit.theta, fit.kind, cov)
    doubt = 1.0
    if fit.kind == "sphere" and gain_sigma > 0:
        extra, soft = gain_doubt(fit.theta, _sphere_samples(fit), fit.residual_ut, gain_sigma,
                                 (s_hat * max(factor, 1.0)) ** 2)
        before = np.sqrt(np.clip(np.diag(cov)[:3], 1e-300, None))
        cov = cov + extra
        doubt = float(np.max(np.sqrt(np.diag(cov)[:3]) / before))
    return {
        "offset_ut": np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None)),
        "field_ut": float(np.sqrt(max(cov[3, 3], 0.0))),
        "soft_iron": soft,
        "gain_doubt_factor": doubt,
        "crlb_offset_ut": np.sqrt(np.clip(np.diag(crlb)[:3], 0.0, None)),
        "sigma_ut": s_hat,
        "autocorrelation_factor": max(factor, 1.0),
        "direction_factor": by_directions,
        "time_block_factor": by_time,
    }


def crlb_offset(m_true_ut: np.ndarray, offset_ut, field_ut: float, noise_ut: float, kind: str = "sphere", W=None) -> np.ndarray:
    """3×3 CRLB of the offset for samples at ``m_true_ut`` under the ``kind`` model."""
    theta = geometric.pack(offset_ut, field_ut, kind, W)
    J = geometric.jacobian(theta, np.asarray(m_true_ut, dtype=np.float64), kind)
    return covariance(J, noise_ut)[:3, :3]


def shape_sigma(cov: np.ndarray) -> float:
    """Largest 1σ of an ellipsoid's shape terms (≈ relative gains) from its parameter covariance
    ([b (3), r, s_xx, s_yy, …], ``geometric``): the fitted terms and s_zz = −s_xx − s_yy, which
    is not a parameter — flat turns determine the x and y gains and leave z's to the few samples
    that tilt, so a gate that looked at the parameters alone would pass an undetermined z gain."""
    shape = np.asarray(cov, dtype=np.float64)[4:, 4:]
    if shape.size == 0:
        return 0.0
    var_zz = shape[0, 0] + shape[1, 1] + 2.0 * shape[0, 1]
    return float(np.sqrt(max(float(np.max(np.diag(shape))), var_zz, 0.0)))


def information_condition(jac: np.ndarray) -> float:
    """Condition number of the information matrix after scaling each parameter to unit
    diagonal (so units do not matter): large = some combination of parameters is not
    determined by this coverage (e.g. c_z and r for flat turns)."""
    return information_condition_of(jac.T @ jac)
