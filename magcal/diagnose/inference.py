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
from scipy import stats


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


def _block_sums(x: np.ndarray, r: np.ndarray, blocks: list[slice]) -> np.ndarray:
    return np.stack([x[b].T @ r[b] for b in blocks])


def pinv_sym(g: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a symmetric PSD matrix (redundant columns get no weight)."""
    if g.size == 0:
        return g
    w, v = np.linalg.eigh(g)
    keep = w > max(w.max(), 1e-300) * 1e-12
    return (v[:, keep] / w[keep]) @ v[:, keep].T


def _block_wald_stat(z: np.ndarray, r0: np.ndarray, blocks: list[slice]):
    """The block-HAC Wald statistic of regressing r0 on z (z already orthogonal to every other
    column): coefficients, (ZᵀZ)⁻¹, the statistic, the effective number of independent blocks
    ν and the F denominator degrees of freedom ν − k + 1."""
    k = z.shape[1]
    ztz = z.T @ z
    zinv = np.linalg.inv(ztz)
    bz = zinv @ (z.T @ r0)
    r = r0 - z @ bz
    # covariance of bz: (ZᵀZ)⁻¹ Σ_b G_b G_bᵀ (ZᵀZ)⁻¹ with G_b = Σ_{i∈b} z_i r_i (Z ⟂ Q)
    gz = _block_sums(z, r, blocks)
    v = zinv @ (gz.T @ gz) @ zinv
    wald = float(bz @ np.linalg.solve(v, bz))
    # effective number of independent blocks (Satterthwaite): a regressor whose weight sits
    # in a few blocks (time, an intermittent current) gives a noisier covariance estimate
    share = np.array([np.trace(zinv @ (z[b].T @ z[b])) for b in blocks]) / k
    nu = 1.0 / float(np.sum(share**2)) - 1.0  # −1: the block sums add up to zero
    return bz, zinv, wald, nu, nu - k + 1


def block_wald(
    x: np.ndarray,
    e: np.ndarray,
    groups: dict[str, np.ndarray],
    n_blocks: int | None = None,
    min_unique: float = 0.2,
) -> dict[str, WaldResult]:
    """For each named column group of x: regress e on all columns and test, with a block-HAC
    Wald statistic, that the group's coefficients are zero.

    Only the group's *identifiable* directions are tested: those whose part not explained by
    the other columns keeps at least ``min_unique`` of its norm (a coverage gate — with
    yaw-only motion most soft-iron directions trade with offset and radius, and their
    second-order residue would otherwise pass for a signal)."""
    n, p = x.shape
    scale = np.sqrt(np.maximum((x * x).sum(axis=0), 1e-300))
    xs = x / scale
    blocks = contiguous_blocks(n, n_blocks or n_test_blocks(n))
    nb = len(blocks)
    out = {}
    gram = xs.T @ xs  # everything below works from Gram blocks: no n-row factorisations
    xte = xs.T @ e
    for name, cols in groups.items():
        cols = np.asarray(cols)
        other = np.setdiff1d(np.arange(p), cols)
        goo = pinv_sym(gram[np.ix_(other, other)])
        xo = xs[:, other]
        xc = xs[:, cols]
        xp = xc - xo @ (goo @ gram[np.ix_(other, cols)])
        ev, vec = np.linalg.eigh(xp.T @ xp)  # singular values² and right singular vectors
        keep = np.sqrt(np.maximum(ev, 0.0)) >= min_unique
        basis_s = vec[:, keep]  # in scaled-column units
        k = int(keep.sum())
        if k == 0 or nb - k < 2:
            out[name] = WaldResult(0.0, max(k, 1), max(nb - k, 1), 1.0, np.zeros(len(cols)), 0.0, basis_s / scale[cols, None])
            continue
        z = xp @ basis_s  # the identifiable part, already orthogonal to the other columns
        r0 = e - xo @ (goo @ xte[other])
        bz, zinv, wald, nu, df2 = _block_wald_stat(z, r0, blocks)
        if df2 < 2:
            out[name] = WaldResult(0.0, k, max(int(df2), 1), 1.0, np.zeros(len(cols)), 0.0, basis_s / scale[cols, None])
            continue
        f = wald * df2 / (k * nu)
        pval = max(float(stats.f.sf(f, k, df2)), _wild_block_p(z, r0, blocks, wald, zinv))
        beta = (basis_s @ bz) / scale[cols]
        # the effect's size is that of the whole term (not only of its part the other columns
        # cannot mimic: a nuisance that shares part of a slow channel must not shrink it)
        size = float(np.sqrt(np.mean((xc @ (basis_s @ bz)) ** 2)))
        out[name] = WaldResult(f, k, int(round(df2)), pval, beta, size, basis_s / scale[cols, None])
    return out


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
    r0 = e - q @ (q.T @ e)
    blocks = contiguous_blocks(n, n_blocks or n_test_blocks(n))
    ratios = []
    for xc in shifted_cols:
        xc = xc / np.sqrt(np.maximum((xc * xc).sum(axis=0), 1e-300))
        z = xc - q @ (q.T @ xc)
        ev, vec = np.linalg.eigh(z.T @ z)
        z = z @ vec[:, ev > 1e-8 * max(float(ev.max()), 1e-300)]  # its identifiable directions
        k = z.shape[1]
        if k == 0:
            continue
        _, _, wald, nu, df2 = _block_wald_stat(z, r0, blocks)
        if df2 < 2:
            continue
        ratios.append(wald * df2 / (k * nu) / float(stats.f.ppf(0.5, k, df2)))
    return max(1.0, float(np.median(ratios))) if ratios else 1.0


_REPS = 1999


def _wild_block_p(z, r0, blocks, wald, zinv, reps: int = _REPS, seed: int = 0x6D61) -> float:
    """Restricted wild block bootstrap of the same Wald statistic: flip the sign of the
    null-model residual block by block (Rademacher), which keeps any within-block
    autocorrelation and the exact shape of the regressors; p = share of draws at least as large.
    Works on block sums only, so it costs O(reps · blocks · k²) whatever n."""
    h = np.stack([z[b].T @ r0[b] for b in blocks])  # (B, k)
    mb = np.stack([z[b].T @ z[b] for b in blocks])  # (B, k, k)
    rng = np.random.default_rng(seed)
    sgn = rng.choice(np.array([-1.0, 1.0]), size=(reps, len(blocks)))
    bz = (sgn @ h) @ zinv  # (R, k)
    g = sgn[:, :, None] * h[None] - np.einsum("bkl,rl->rbk", mb, bz)
    s = np.einsum("rbk,rbl->rkl", g, g)
    v = zinv[None] @ s @ zinv[None]
    try:
        w = np.einsum("rk,rk->r", bz, np.linalg.solve(v, bz[:, :, None])[:, :, 0])
    except np.linalg.LinAlgError:
        return 1.0
    return float((1 + np.sum(w >= wald * (1 - 1e-12))) / (reps + 1))


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
