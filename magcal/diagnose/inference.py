"""Autocorrelation-robust tests, family-wise error control and contiguous held-out blocks.

Residuals of real recordings are autocorrelated (docs/physics.md, "Real residuals"), so ordinary F-tests "find" an
effect in any smooth covariate. The Wald test here uses a batch-means (block-sum) HAC
covariance: the regression scores are summed over B contiguous time blocks and the covariance
is estimated from those B sums; the statistic is referred to an F distribution, which stays honest
when the autocorrelation is shorter than a block. The denominator degrees of freedom are the
effective number of blocks (Satterthwaite), not the count: a regressor whose weight sits in a
few blocks gets a correspondingly noisier covariance. Where the recording's residual wanders
on time scales longer than a block, the same test is run on draws of the recording's twin
(magcal.diagnose.null) and the statistic is calibrated against them (``calibrated``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..fit.tails import f_isf, f_sf


def contiguous_blocks(n: int, k: int) -> list[slice]:
    """k contiguous, nearly equal slices covering range(n)."""
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


BLOCKS_PER_ROOT_N = 0.5  # test blocks per √n samples, between MIN_BLOCKS and MAX_BLOCKS
MIN_BLOCKS, MAX_BLOCKS = 12, 40


def n_test_blocks(n: int) -> int:
    return int(np.clip(np.sqrt(n) * BLOCKS_PER_ROOT_N, MIN_BLOCKS, MAX_BLOCKS))


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
    null_f: np.ndarray | None = field(default=None, repr=False)  # (K,) F of the same test on twin draws
    null_f_white: np.ndarray | None = field(default=None, repr=False)  # (K,) the same draws without wander
    null_beta: np.ndarray | None = field(default=None, repr=False)  # (K, n_cols) their coefficients
    inflation: float = 1.0  # λ: how far the twin draws' F runs above the F distribution (calibrated)

    @property
    def null_spread(self) -> np.ndarray | None:
        """The mean of ββᵀ over the twin draws: the coefficient's spread when the term is absent
        and the residual wanders as the recording's twin does (None without draws)."""
        if self.null_beta is None or not len(self.null_beta):
            return None
        return self.null_beta.T @ self.null_beta / len(self.null_beta)


def calibrated(result: WaldResult) -> WaldResult:
    """The test judged against its twin draws: its F statistic divided by λ ≥ 1 (p is never
    lowered), how far the draws' F runs above the same draws' F without the twin's wander (the
    mean over the mean: paired draws share their white noise, so λ is exactly 1 for a twin
    without wander and its estimate is not a chance excess of two dozen draws over the F
    distribution). The twin keeps the recording's own wander, so a slow channel that lines up
    with it by chance is judged against how often such lining up happens here, not against
    white noise."""
    if result.null_f is None or not len(result.null_f) or result.untestable:
        return result
    if result.null_f_white is not None and len(result.null_f_white):
        lam = float(np.mean(result.null_f)) / max(float(np.mean(result.null_f_white)), 1e-300)
    else:
        lam = float(np.median(result.null_f)) / float(f_isf(0.5, result.df1, result.df2))
    lam = max(1.0, lam)
    p = float(f_sf(result.f / lam, result.df1, result.df2))
    return replace(result, p=max(result.p, p), inflation=lam)


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
class _Hac:
    """What a group's block-HAC Wald test needs that depends on its columns alone, so that the
    same test runs on the recording's residual and on each of its twin draws."""

    z: np.ndarray  # (n, k) the tested columns, orthogonal to the nuisance
    blocks: list
    zinv: np.ndarray  # (ZᵀZ)⁻¹
    a: np.ndarray  # (ZᵀZ)⁻¹ T: the block scores' map to the coefficient covariance
    nu: float  # effective number of independent blocks
    kept_variance: float  # smallest share of the iid variance the block estimate keeps
    fallback: bool  # too few effective blocks: the autocorrelation-widened iid covariance instead

    @property
    def k(self) -> int:
        return self.z.shape[1]

    @property
    def df2(self) -> float:
        """F denominator degrees of freedom: ν − k + 1 (B − k with the fallback)."""
        return (len(self.blocks) - 1 if self.fallback else self.nu) - self.k + 1


def _hac(z: np.ndarray, blocks: list[slice], nuis: _Nuisance) -> _Hac:
    """The block-HAC test of columns z (already orthogonal to the nuisance columns).

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
    s_b = np.stack([z[b].T @ z[b] for b in blocks])
    p_b = np.stack([z[b].T @ nuis.x[b] for b in blocks])
    e_b = s_b - (p_b @ nuis.ginv) @ p_b.transpose(0, 2, 1) - s_b @ zinv @ s_b  # P_b N⁻¹ P_bᵀ as matrix products
    e_sum = e_b.sum(axis=0)
    root = _sqrt_sym(zinv, 0.5)
    kept = float(np.linalg.eigvalsh(root @ e_sum @ root).min())
    t = _sqrt_sym(ztz, 0.5) @ _sqrt_sym(e_sum, -0.5)
    share = np.einsum("kl,blk->b", zinv, e_b)
    share = share / share.sum()
    nu = 1.0 / float(np.sum(share**2)) - 1.0
    fallback = kept < MIN_KEPT_VARIANCE or nu - k + 1 < 2
    return _Hac(z, blocks, zinv, zinv @ t, nu, kept, fallback)


def _hac_wald(h: _Hac, r0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The statistic for residual columns r0 (n, K), each orthogonal to the nuisance: the
    coefficients (k, K), their covariances (K, k, k), Wald statistics (K,) and, with the
    fallback, the autocorrelation factors (K,) (else None).

    With ``h.fallback`` (the block covariance rests on too few effective blocks, or the
    nuisances leave it too little block-level variation) the independent-noise covariance
    σ²(ZᵀZ)⁻¹ is widened by the residual's own autocorrelation factor λ (the long-run over the
    plain variance, from the sums of the residual over all blocks)."""
    z, n = h.z, len(r0)
    bz = h.zinv @ (z.T @ r0)
    r = r0 - z @ bz
    if h.fallback:
        sums = np.stack([r[b].sum(axis=0) for b in h.blocks])  # (B, K)
        sigma2 = np.einsum("ik,ik->k", r, r) / max(n - h.k, 1)
        lam = np.maximum(1.0, np.sum(sums**2, axis=0) / (np.maximum(sigma2, 1e-300) * n))
        cov = (lam * sigma2)[:, None, None] * h.zinv[None]
    else:
        lam = None
        g = np.stack([z[b].T @ r[b] for b in h.blocks])  # (B, k, K)
        gg = np.einsum("bkK,blK->Kkl", g, g)
        cov = h.a[None] @ gg @ h.a.T[None]
    wald = np.einsum("kK,Kk->K", bz, np.linalg.solve(cov, bz.T[:, :, None])[:, :, 0])
    return bz, cov, wald, lam


def _fallback_text(h: _Hac, lam: float) -> str:
    return (f"the block covariance rested on {max(h.nu, 0.0):.1f} effective blocks (its information sits in a few "
            f"stretches of the recording; it kept {100 * max(h.kept_variance, 0.0):.0f} % of its expected variation), "
            f"so the independent-noise covariance widened by the residual's autocorrelation factor {lam:.2f} was used")


def _untested(k: int, nb: int, ncols: int, basis: np.ndarray, why: str) -> "WaldResult":
    return WaldResult(0.0, max(k, 1), max(nb - k, 1), 1.0, np.zeros(ncols), 0.0, basis, untestable=why)


def block_wald(
    x: np.ndarray,
    e: np.ndarray,
    groups: dict[str, np.ndarray],
    n_blocks: int | None = None,
    min_unique: float | dict = 0.2,
    null: tuple | None = None,
) -> dict[str, WaldResult]:
    """For each named column group of x: regress e on all columns and test, with a block-HAC
    Wald statistic, that the group's coefficients are zero.

    Only the group's *identifiable* directions are tested: those whose part not explained by
    the other columns keeps at least ``min_unique`` of its norm (a coverage gate — with
    yaw-only motion most soft-iron directions trade with offset and radius, and their
    second-order residue would otherwise pass for a signal; a dict gives it per group, 0.2 for
    a group it does not name); its other directions are nuisances of the test.

    ``null``: (with_wander, white), each (n, K): residuals drawn under the null hypothesis
    (the recording's twin without the tested terms, magcal.diagnose.null), and the same draws
    without the twin's wander; the same test is run on each and the result carries their F
    statistics and the coefficients of the first, against which ``calibrated`` judges it."""
    n, p = x.shape
    scale = np.sqrt(np.maximum((x * x).sum(axis=0), 1e-300))
    xs = x / scale
    blocks = contiguous_blocks(n, n_blocks or n_test_blocks(n))
    gram = xs.T @ xs
    ys = e[:, None] if null is None else np.column_stack([e, *null])  # the residual columns every group tests
    out = {}
    for name, cols in groups.items():
        cols = np.asarray(cols)
        other = np.setdiff1d(np.arange(p), cols)
        nuis = _Nuisance(xs[:, other], pinv_sym(gram[np.ix_(other, other)]))
        xc = xs[:, cols]
        xp = nuis.project_out(xc)
        ev, vec = np.linalg.eigh(xp.T @ xp)  # singular values² and right singular vectors
        floor = min_unique.get(name, 0.2) if isinstance(min_unique, dict) else min_unique
        keep = np.sqrt(np.maximum(ev, 0.0)) >= floor
        basis = vec[:, keep] / scale[cols, None]
        out[name] = _test_group(xp, vec, keep, ys, nuis, blocks, xc, basis, scale[cols], null)
    return out


def _test_group(xp, vec, keep, ys, nuis, blocks, xc, basis, col_scale, null) -> WaldResult:
    """One group's test on its identifiable directions (see block_wald), of the residual
    columns ``ys`` (the recording's, then the twin's draws with and without its wander)."""
    k, nb, ncols = int(keep.sum()), len(blocks), len(keep)
    if k == 0:
        return _untested(0, nb, ncols, basis, "directions")
    if k < ncols:
        # the group's own directions that the other columns mimic are nuisances of the test,
        # not ignored: left in the residual they would leak into the tested directions
        nuis = nuis.extended(xp @ vec[:, ~keep])
    z = xp @ vec[:, keep]  # the identifiable part, orthogonal to the other columns
    z = nuis.project_out(z) if k < ncols else z
    h = _hac(z, blocks, nuis)
    r0 = nuis.project_out(ys)
    bz, cov, wald, lam = _hac_wald(h, r0)
    df2 = h.df2
    f_of = wald * df2 / (k * (len(blocks) - 1 if h.fallback else h.nu))
    f = float(f_of[0])
    to_group = vec[:, keep] / col_scale[:, None]  # tested coordinates → the group's column units
    fallback = _fallback_text(h, float(lam[0])) if h.fallback else ""
    # the effect's size is that of the whole term (not only of its part the other columns
    # cannot mimic: a nuisance that shares part of a slow channel must not shrink it)
    size = float(np.sqrt(np.mean((xc @ (vec[:, keep] @ bz[:, 0])) ** 2)))
    nulls = {}
    if null is not None:
        count = null[0].shape[1]
        nulls = {"null_f": f_of[1 : 1 + count], "null_f_white": f_of[1 + count :],
                 "null_beta": (to_group @ bz[:, 1 : 1 + count]).T}
    return WaldResult(f, k, int(round(df2)), float(f_sf(f, k, df2)), to_group @ bz[:, 0], size, basis,
                      cov=to_group @ cov[0] @ to_group.T, nu=h.nu, fallback=fallback, **nulls)


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
