"""Autocorrelation-robust tests, family-wise error control and contiguous held-out blocks.

Residuals of real recordings are autocorrelated (docs/physics.md, "Real residuals"), so ordinary F-tests "find" an
effect in any smooth covariate. The Wald test here uses a batch-means (block-sum) HAC
covariance: the regression scores are summed over B contiguous time blocks and the covariance
is estimated from those B sums; the statistic is referred to an F distribution, which stays honest
when the autocorrelation is shorter than a block. The denominator degrees of freedom are the
effective number of blocks (Satterthwaite), not the count: a regressor whose weight sits in a
few blocks gets a correspondingly noisier covariance. Because slow motion makes the block
scores nearly rank-one, the p-value is the larger of that F approximation and a restricted
wild block bootstrap of the same statistic (sign flips of whole blocks).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .distributions import f_isf, f_sf


def contiguous_blocks(n: int, k: int) -> list[slice]:
    """k contiguous, nearly equal slices covering range(n)."""
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def n_test_blocks(n: int) -> int:
    return int(np.clip(np.sqrt(n) / 2.0, 12, 40))


@dataclass(frozen=True)
class WaldResult:
    f: float
    df1: int
    df2: int
    p: float
    beta: np.ndarray  # coefficients of the group's columns (original units; 0 off the tested subspace)
    effect_rms_ut: float
    basis: np.ndarray  # (n_cols, k) the identifiable directions tested, in the group's column units
    cov: np.ndarray | None = None  # (n_cols, n_cols) block-HAC covariance of beta (0 off the tested subspace)
    nu: float = float("nan")  # effective number of independent blocks behind cov
    untestable: str = ""  # why the group could not be tested: "directions", "blocks", or ""
    fallback: str = ""  # when the block covariance could not carry the test, what was used instead


def _block_sums(x: np.ndarray, r: np.ndarray, blocks: list[slice]) -> np.ndarray:
    return np.stack([x[b].T @ r[b] for b in blocks])


def pinv_sym(g: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a symmetric PSD matrix (redundant columns get no weight)."""
    if g.size == 0:
        return g
    w, v = np.linalg.eigh(g)
    keep = w > max(w.max(), 1e-300) * 1e-12
    return (v[:, keep] / w[keep]) @ v[:, keep].T


def _sqrt_sym(a: np.ndarray, power: float) -> np.ndarray:
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    return (v * np.maximum(w, 1e-300) ** power) @ v.T


@dataclass(frozen=True)
class _Nuisance:
    """The other columns of a test: x (n, r) and the pseudo-inverse of their Gram matrix."""

    x: np.ndarray
    ginv: np.ndarray

    def project_out(self, y: np.ndarray) -> np.ndarray:
        return y - self.x @ (self.ginv @ (self.x.T @ y))

    def extended(self, q: np.ndarray) -> "_Nuisance":
        """With columns q added (q orthogonal to x)."""
        g = pinv_sym(q.T @ q)
        r = self.ginv.shape[0]
        ginv = np.zeros((r + len(g), r + len(g)))
        ginv[:r, :r], ginv[r:, r:] = self.ginv, g
        return _Nuisance(np.concatenate([self.x, q], axis=1), ginv)


# the block-HAC variance estimate keeps less than this share of its expectation under
# independent noise (the nuisance columns take most of the block-level variation): no test
MIN_KEPT_VARIANCE = 0.05


@dataclass(frozen=True)
class _Stat:
    bz: np.ndarray  # coefficients of z
    cov: np.ndarray  # their (bias-corrected) block-HAC covariance
    wald: float
    nu: float  # effective number of independent blocks
    df2: float  # F denominator degrees of freedom ν − k + 1
    kept_variance: float  # smallest share of the iid variance the block estimate keeps
    parts: tuple  # what the wild bootstrap needs: (h_b, c_b, P_b, S_b, zinv, T, N⁻¹)


def _block_wald_stat(z: np.ndarray, r0: np.ndarray, blocks: list[slice], nuis: _Nuisance) -> _Stat:
    """The block-HAC Wald statistic of regressing r0 on z (z and r0 already orthogonal to the
    nuisance columns).

    The batch-means covariance (ZᵀZ)⁻¹ Σ_b G_b G_bᵀ (ZᵀZ)⁻¹, G_b = Σ_{i∈b} z_i r_i, is biased
    low when nuisance columns are fitted: the residual r is orthogonal to every nuisance column,
    and a smooth nuisance (direction harmonics, wander) that resembles z within each block
    forces the block scores G_b to cancel. Under independent noise E[Σ G_b G_bᵀ] = σ² E with
    E = Σ_b (S_b − P_b N⁻¹ P_bᵀ − S_b (ZᵀZ)⁻¹ S_b), S_b = Z_bᵀZ_b, P_b = Z_bᵀX_b (X the nuisance,
    N its Gram matrix); the estimate is rescaled by T = (ZᵀZ)^½ E^−½ so that it is unbiased
    there (the bias-reduced cluster covariance of Bell & McCaffrey 2002, in matrix form).
    ν, the effective number of independent blocks, is Satterthwaite's from each block's share
    of E."""
    k = z.shape[1]
    ztz = z.T @ z
    zinv = np.linalg.inv(ztz)
    bz = zinv @ (z.T @ r0)
    r = r0 - z @ bz
    s_b = np.stack([z[b].T @ z[b] for b in blocks])
    p_b = np.stack([z[b].T @ nuis.x[b] for b in blocks])
    e_b = s_b - np.einsum("bkr,rs,bls->bkl", p_b, nuis.ginv, p_b) - s_b @ zinv @ s_b
    e_sum = e_b.sum(axis=0)
    root = _sqrt_sym(zinv, 0.5)
    kept = float(np.linalg.eigvalsh(root @ e_sum @ root).min())
    t = _sqrt_sym(ztz, 0.5) @ _sqrt_sym(e_sum, -0.5)
    g = _block_sums(z, r, blocks)
    cov = zinv @ t @ (g.T @ g) @ t.T @ zinv
    wald = float(bz @ np.linalg.solve(cov, bz))
    share = np.einsum("kl,blk->b", zinv, e_b)
    share = share / share.sum()
    nu = 1.0 / float(np.sum(share**2)) - 1.0
    h_b = _block_sums(z, r0, blocks)
    c_b = _block_sums(nuis.x, r0, blocks)
    return _Stat(bz, cov, wald, nu, nu - k + 1, kept, (h_b, c_b, p_b, s_b, zinv, t, nuis.ginv))


def _untested(k: int, nb: int, ncols: int, basis: np.ndarray, why: str) -> "WaldResult":
    return WaldResult(0.0, max(k, 1), max(nb - k, 1), 1.0, np.zeros(ncols), 0.0, basis, untestable=why)


def block_wald(
    x: np.ndarray,
    e: np.ndarray,
    groups: dict[str, np.ndarray],
    n_blocks: int | None = None,
    min_unique: float | dict = 0.2,
    bootstrap: bool = True,
) -> dict[str, WaldResult]:
    """For each named column group of x: regress e on all columns and test, with a block-HAC
    Wald statistic, that the group's coefficients are zero.

    Only the group's *identifiable* directions are tested: those whose part not explained by
    the other columns keeps at least ``min_unique`` of its norm (a coverage gate — with
    yaw-only motion most soft-iron directions trade with offset and radius, and their
    second-order residue would otherwise pass for a signal; a dict gives it per group, 0.2 for
    a group it does not name); its other directions are
    nuisances of the test. ``bootstrap``: also check a test that could pass against the wild
    block bootstrap (False where the statistic is calibrated another way)."""
    n, p = x.shape
    scale = np.sqrt(np.maximum((x * x).sum(axis=0), 1e-300))
    xs = x / scale
    blocks = contiguous_blocks(n, n_blocks or n_test_blocks(n))
    gram = xs.T @ xs
    out = {}
    for name, cols in groups.items():
        cols = np.asarray(cols)
        other = np.setdiff1d(np.arange(p), cols)
        nuis = _Nuisance(xs[:, other], pinv_sym(gram[np.ix_(other, other)]))
        xc = xs[:, cols]
        xp = nuis.project_out(xc)
        ev, vec = np.linalg.eigh(xp.T @ xp)  # singular values² and right singular vectors
        keep = np.sqrt(np.maximum(ev, 0.0)) >= (min_unique.get(name, 0.2) if isinstance(min_unique, dict) else min_unique)
        basis = vec[:, keep] / scale[cols, None]
        out[name] = _test_group(xp, vec, keep, e, nuis, blocks, xc, basis, scale[cols], bootstrap)
    return out


def _test_group(xp, vec, keep, e, nuis, blocks, xc, basis, col_scale, bootstrap: bool) -> WaldResult:
    """One group's test on its identifiable directions (see block_wald)."""
    k, nb, ncols = int(keep.sum()), len(blocks), len(keep)
    if k == 0:
        return _untested(0, nb, ncols, basis, "directions")
    if k < ncols:
        # the group's own directions that the other columns mimic are nuisances of the test,
        # not ignored: left in the residual they would leak into the tested directions
        nuis = nuis.extended(xp @ vec[:, ~keep])
    z = xp @ vec[:, keep]  # the identifiable part, orthogonal to the other columns
    z = nuis.project_out(z) if k < ncols else z
    r0 = nuis.project_out(e)
    st = _block_wald_stat(z, r0, blocks, nuis)
    fallback = ""
    if st.kept_variance < MIN_KEPT_VARIANCE or st.df2 < 2:
        st, fallback = _scalar_autocorrelation_stat(z, r0, blocks, st)
    f = st.wald * st.df2 / (k * st.nu)
    pval = float(f_sf(f, k, st.df2))
    if bootstrap and not fallback and pval <= BOOTSTRAP_BELOW:
        # only a test that could pass is checked against the bootstrap (p is the larger of the two)
        pval = max(pval, _wild_block_p(st))
    basis_s = vec[:, keep]
    beta = (basis_s @ st.bz) / col_scale
    # the effect's size is that of the whole term (not only of its part the other columns
    # cannot mimic: a nuisance that shares part of a slow channel must not shrink it)
    size = float(np.sqrt(np.mean((xc @ (basis_s @ st.bz)) ** 2)))
    cov = (basis_s / col_scale[:, None]) @ st.cov @ (basis_s / col_scale[:, None]).T
    return WaldResult(f, k, int(round(st.df2)), pval, beta, size, basis, cov=cov, nu=st.nu, fallback=fallback)


def _scalar_autocorrelation_stat(z: np.ndarray, r0: np.ndarray, blocks: list[slice], hac: _Stat) -> tuple[_Stat, str]:
    """When the block covariance of a term rests on too few effective blocks (its information
    sits in a few stretches of the recording) or the nuisances leave it too little block-level
    variation, the test is not refused: the independent-noise covariance σ²(ZᵀZ)⁻¹ is widened by
    the residual's own autocorrelation factor λ (the long-run over the plain variance, from the
    sums of the residual over all blocks, B − 1 degrees of freedom). Returns the statistic and a
    sentence saying which gate was met and why."""
    k = z.shape[1]
    ztz = z.T @ z
    zinv = np.linalg.inv(ztz)
    bz = zinv @ (z.T @ r0)
    r = r0 - z @ bz
    sums = np.array([r[b].sum() for b in blocks])
    sizes = np.array([b.stop - b.start for b in blocks], np.float64)
    sigma2 = float(r @ r) / max(len(r) - k, 1)
    lam = max(1.0, float(np.sum(sums**2) / (sigma2 * sizes.sum())))
    cov = lam * sigma2 * zinv
    wald = float(bz @ np.linalg.solve(cov, bz))
    nu = float(len(blocks) - 1)
    why = (f"the block covariance rested on {max(hac.nu, 0.0):.1f} effective blocks (its information sits in a few "
           f"stretches of the recording; it kept {100 * max(hac.kept_variance, 0.0):.0f} % of its expected variation), "
           f"so the independent-noise covariance widened by the residual's autocorrelation factor {lam:.2f} was used")
    return _Stat(bz, cov, wald, nu, nu - k + 1, 1.0, ()), why


def shift_inflation(x_other: np.ndarray, e: np.ndarray, shifted_cols, n_blocks: int | None = None) -> float:
    """λ ≥ 1: how much larger the block-HAC F statistic of a channel's columns runs on this
    recording's own residual, once the channel is circularly shifted out of alignment (so it
    cannot carry the effect), than the F distribution expects — the median of F / median(F).

    Real residuals hold structure at every time scale; when some of it is shorter than the
    test's blocks, an unrelated channel that switches on the same scale collects it and the F
    approximation over-rejects. Dividing the aligned statistic by λ calibrates it against this
    recording's own null (shifted channels keep their time structure exactly).
    ``shifted_cols``: an iterable of (n, k) regressor arrays of the shifted channel."""
    n = len(e)
    scale = np.sqrt(np.maximum((x_other * x_other).sum(axis=0), 1e-300))
    q, rr = np.linalg.qr(x_other / scale)
    q = q[:, np.abs(np.diag(rr)) > 1e-10 * max(float(np.max(np.abs(np.diag(rr)))), 1e-300)]
    nuis = _Nuisance(q, np.eye(q.shape[1]))
    r0 = nuis.project_out(e)
    blocks = contiguous_blocks(n, n_blocks or n_test_blocks(n))
    ratios = []
    for xc in shifted_cols:
        xc = xc / np.sqrt(np.maximum((xc * xc).sum(axis=0), 1e-300))
        z = nuis.project_out(xc)
        ev, vec = np.linalg.eigh(z.T @ z)
        z = z @ vec[:, ev > 1e-8 * max(float(ev.max()), 1e-300)]  # its identifiable directions
        k = z.shape[1]
        if k == 0:
            continue
        st = _block_wald_stat(z, r0, blocks, nuis)
        if st.df2 < 2 or st.kept_variance < MIN_KEPT_VARIANCE:
            continue
        ratios.append(st.wald * st.df2 / (k * st.nu) / float(f_isf(0.5, k, st.df2)))
    return max(1.0, float(np.median(ratios))) if ratios else 1.0


def shifted_spread(x_all: np.ndarray, e: np.ndarray, shifted_cols) -> np.ndarray | None:
    """The spread of a channel term's coefficient when the channel cannot carry the effect:
    the mean of ββᵀ over circularly shifted copies of its columns, each regressed on this
    recording's residual with every column of ``x_all`` (the aligned channel's included, so
    an effect that is there does not widen its own spread). Shifted copies keep the channel's
    own time structure, so this is what slow wander and fast residual structure lend a
    coefficient here — the empirical counterpart of its covariance. None without copies."""
    scale = np.sqrt(np.maximum((x_all * x_all).sum(axis=0), 1e-300))
    q, rr = np.linalg.qr(x_all / scale)
    q = q[:, np.abs(np.diag(rr)) > 1e-10 * max(float(np.max(np.abs(np.diag(rr)))), 1e-300)]
    nuis = _Nuisance(q, np.eye(q.shape[1]))
    r0 = nuis.project_out(e)
    betas = []
    for xc in shifted_cols:
        z = nuis.project_out(xc)
        betas.append(np.linalg.lstsq(z, r0, rcond=1e-10)[0])
    if not betas:
        return None
    b = np.array(betas)
    return b.T @ b / len(b)


_REPS = 1999
BOOTSTRAP_BELOW = 0.05  # above this the F approximation alone decides (no test passes there)


def _wild_block_p(st: _Stat, reps: int = _REPS, seed: int = 0x6D61) -> float:
    """Restricted wild block bootstrap of the same Wald statistic: flip the sign of the
    null-model residual block by block (Rademacher), which keeps any within-block
    autocorrelation and the exact shape of the regressors, refit z and the nuisance to each
    draw and studentise it the same way; p = the share of draws at least as large. Works on
    block sums only, so it costs O(reps · blocks · k · r) whatever n."""
    h_b, c_b, p_b, s_b, zinv, t, ginv = st.parts
    nb, k, r = p_b.shape
    rng = np.random.default_rng(seed)
    sgn = rng.choice(np.array([-1.0, 1.0]), size=(reps, nb))
    bz = (sgn @ h_b) @ zinv  # (R, k)
    nuis = (sgn @ c_b) @ ginv  # (R, r): the nuisance refitted to each draw
    g = sgn[:, :, None] * h_b[None]
    g -= (nuis @ p_b.transpose(2, 0, 1).reshape(r, nb * k)).reshape(reps, nb, k)
    g -= (bz @ s_b.transpose(2, 0, 1).reshape(k, nb * k)).reshape(reps, nb, k)
    g = g @ t.T
    v = zinv[None] @ (g.transpose(0, 2, 1) @ g) @ zinv[None]
    try:
        w = np.einsum("rk,rk->r", bz, np.linalg.solve(v, bz[:, :, None])[:, :, 0])
    except np.linalg.LinAlgError:
        return 1.0
    exceed = int(np.sum(w >= st.wald * (1 - 1e-12)))
    # no draw as large: the bootstrap does not contradict the F approximation at any level it
    # can resolve, and must not cap p at 1/(reps + 1) (with many tests Holm asks for less)
    return float((1 + exceed) / (reps + 1)) if exceed else 0.0


def phase_surrogates(x: np.ndarray, count: int, rng) -> np.ndarray:
    """(count, n) copies of x with the same power spectrum and mean and random Fourier phases
    (Theiler et al. 1992): series as slow and as smooth as x, unrelated to anything else."""
    x = np.asarray(x, np.float64)
    n = len(x)
    spec = np.abs(np.fft.rfft(x - x.mean()))
    ph = rng.uniform(0.0, 2 * np.pi, (count, len(spec)))
    ph[:, 0] = 0.0
    if n % 2 == 0:
        ph[:, -1] = 0.0
    return np.fft.irfft(spec * np.exp(1j * ph), n=n, axis=1) + x.mean()


def surrogate_p(x_other: np.ndarray, e: np.ndarray, columns, x: np.ndarray, count: int, seed: int) -> float:
    """p-value of a channel's regression sum of squares on the residual (the other columns
    fitted out) against the same for ``count`` phase-randomised surrogates of the channel.
    ``columns(x)`` builds the channel's (n, k) columns from channel values x. A slow channel
    lines up with a slow wander by chance as often as its surrogates do; one that carries an
    effect lines up better than all of them."""
    scale = np.sqrt(np.maximum((x_other * x_other).sum(axis=0), 1e-300))
    q, rr = np.linalg.qr(x_other / scale)
    q = q[:, np.abs(np.diag(rr)) > 1e-10 * max(float(np.max(np.abs(np.diag(rr)))), 1e-300)]
    nuis = _Nuisance(q, np.eye(q.shape[1]))
    r0 = nuis.project_out(e)

    def ss(values):
        z = nuis.project_out(columns(values))
        zr = z.T @ r0
        return float(zr @ np.linalg.lstsq(z.T @ z, zr, rcond=1e-12)[0])

    observed = ss(x)
    others = [ss(v) for v in phase_surrogates(x, count, np.random.default_rng(seed))]
    return float((1 + sum(o >= observed for o in others)) / (count + 1))


def holm(pvals: dict[str, float], alpha: float) -> dict[str, bool]:
    """Holm's step-down procedure: which hypotheses are rejected at family-wise level alpha."""
    order = sorted(pvals, key=lambda k: pvals[k])
    m = len(order)
    out = {k: False for k in order}
    for i, k in enumerate(order):
        if pvals[k] <= alpha / (m - i):
            out[k] = True
        else:
            break
    return out


def heldout_sse(
    x: np.ndarray, e: np.ndarray, subsets: dict[str, np.ndarray], k_folds: int = 5, interleave: int = 1
) -> dict[str, float]:
    """Held-out mean squared residual of the linearised model restricted to each column
    subset: fit on all but one fold, predict that fold, over k_folds folds. A fold is one
    contiguous block (``interleave`` 1) or ``interleave`` contiguous blocks spread over the
    recording (k_folds·interleave blocks dealt round-robin), so a smooth nuisance in time is
    interpolated into a held-out block rather than extrapolated."""
    n = len(e)
    blocks = contiguous_blocks(n, k_folds * max(int(interleave), 1))
    scale = np.sqrt(np.maximum((x * x).sum(axis=0), 1e-300))
    xs = x / scale

    def part(bs):
        a = sum(xs[b].T @ xs[b] for b in bs)
        return a, sum(xs[b].T @ e[b] for b in bs), float(sum(e[b] @ e[b] for b in bs))

    parts = [part(blocks[i :: k_folds]) for i in range(min(k_folds, len(blocks)))]
    tot_a = sum(p[0] for p in parts)
    tot_b = sum(p[1] for p in parts)
    out = {}
    for name, cols in subsets.items():
        cols = np.asarray(cols)
        sse = 0.0
        for a_f, b_f, ee_f in parts:
            a_tr = (tot_a - a_f)[np.ix_(cols, cols)]
            b_tr = (tot_b - b_f)[cols]
            beta = np.linalg.pinv(a_tr, rcond=1e-10) @ b_tr
            sse += ee_f - 2 * beta @ b_f[cols] + beta @ a_f[np.ix_(cols, cols)] @ beta
        out[name] = float(np.sqrt(max(sse, 0.0) / n))
    return out
