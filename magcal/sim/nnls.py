"""Non-negative least squares in numpy: min ‖A x − b‖ subject to x ≥ 0.

The active-set algorithm of Lawson and Hanson ("Solving Least Squares Problems", SIAM 1995,
chapter 23), on unit columns (x ≥ 0 does not care for a column's scale), each subproblem
solved on the free columns by the normal equations when the design is well conditioned and
by an orthogonal least-squares solve otherwise. It gives the solution scipy.optimize.nnls
gives (the same algorithm), without importing the optimiser package, which costs a command
most of its start-up.
"""

from __future__ import annotations

import numpy as np


def nnls(a: np.ndarray, b: np.ndarray, maxiter: int | None = None, start: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(x, ‖A x − b‖) with x ≥ 0 minimising the residual. ``maxiter`` (default 3 × columns)
    bounds the inner steps; RuntimeError when they run out. ``start``: a guess at the columns
    that are positive at the optimum (boolean, e.g. those of a nearby problem's solution in a
    sequence of them): when the least-squares solution on those columns is positive the
    active-set steps start from it instead of from zero (each column freed on the way there
    is a solve saved) — the optimum, and so the set of free columns it ends with, is the
    same, and x is then the same solve on that set."""
    a0 = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    # x ≥ 0 is unchanged by a positive scale of each column: solved on unit columns, so that
    # one tolerance serves columns of any size
    norm = np.linalg.norm(a0, axis=0)
    norm[norm == 0] = 1.0
    a = a0 / norm
    m, n = a.shape
    maxiter = 3 * n if maxiter is None else maxiter
    maxiter += n  # the outer steps (one per column freed) are counted too
    x = np.zeros(n)
    free = np.zeros(n, dtype=bool)
    tol = 10.0 * max(m, n) * np.finfo(np.float64).eps * max(float(np.linalg.norm(b)), 1e-300)
    steps = 0
    solve = _solver(a, b)
    if start is not None and np.any(start):
        s = solve(np.asarray(start, dtype=bool))
        if np.all(s[start] > tol):
            free, x = np.array(start, dtype=bool), s
    w = a.T @ (b - a @ x)
    while not free.all():
        steps += 1
        j = int(np.argmax(np.where(free, -np.inf, w)))
        if w[j] <= tol:
            break
        free[j] = True
        s = solve(free)
        while np.any(s[free] <= 0):
            steps += 1
            if steps > maxiter:
                raise RuntimeError("nnls: the maximum number of iterations was reached")
            blocked = free & (s <= 0)
            gap = x[blocked] - s[blocked]  # ≥ 0: x ≥ 0 ≥ s there
            alpha = float(np.min(np.divide(x[blocked], gap, out=np.zeros_like(gap), where=gap > 0)))
            x += alpha * (s - x)
            free &= x > tol
            x[~free] = 0.0
            s = solve(free)
        x = s
        w = a.T @ (b - a @ x)
    x = x / norm
    return x, float(np.linalg.norm(a0 @ x - b))


def _solver(a: np.ndarray, b: np.ndarray):
    """free → the unconstrained least-squares solution on the free columns, zero elsewhere.
    On a well-conditioned design (unit columns, singular values within 1e4 of each other) from
    the normal equations, whose error (condition² × ε ≤ 1e-8) is far inside any use here and
    which cost a tenth of an orthogonal solve; otherwise by the orthogonal solve itself. The
    singular values are read as the square roots of the Gram matrix's eigenvalues (the Gram
    matrix is the normal equations' own; its eigenvalues are exact to ε × the largest, far
    inside the 1e-8 the test asks of their ratio)."""
    gram = a.T @ a
    ev = np.linalg.eigvalsh(gram) if a.shape[0] >= a.shape[1] and a.shape[1] else np.zeros(0)
    if len(ev) and ev[0] > 1e-8 * ev[-1]:
        rhs = a.T @ b

        def normal(free):
            s = np.zeros(a.shape[1])
            idx = np.flatnonzero(free)  # an index array: a third of np.ix_'s cost, the same submatrix
            s[idx] = np.linalg.solve(gram[idx[:, None], idx], rhs[idx])
            return s

        return normal

    def orthogonal(free):
        s = np.zeros(a.shape[1])
        s[free] = np.linalg.lstsq(a[:, free], b, rcond=None)[0]
        return s

    return orthogonal
