"""Can the training part foretell what fit's direction balance does forward in time?

    MAGCAL_REAL_DATA=… python bench/balance_foresight.py [--splits 0.3,0.5,0.7] [--only NAME]

``fit --model auto`` gives an ellipsoid the direction balance (``pipeline._balanced``) unless its
held-out time blocks put the unweighted fit ``holdout.BALANCE_MARGIN`` times ahead. Whether the
balance helps is what decides most of ``bench/model_choice.py``'s cells above 1.02, and what the
static race against MotionCal rests on. This bench asks, per cell of the open recordings of
``model_choice.py`` (the sealed ones are never read here), whether anything the training part
shows foretells the balance's forward effect:

* forward   — held-out spread of the balanced ÷ the unweighted fit of the fullest determined
              ellipsoid, judged on the part after the split (what model_choice.py measures);
* blocks    — the same ratio on the training part's own five held-out time blocks, all their
              samples (what ``holdout`` keeps or drops the balance by);
* chained   — the same ratio forward-chained over those blocks: each refitted on the blocks
              before block k only and judged on block k (k = 2…5), the geometric mean of the
              per-block ratios (blocks where either refit failed left out) — the training
              part asked the bench's own question, "fit on the past, judge the future";
* moved     — how far the balance moves the offset (µT), beside how far the unweighted fit of the
              training part lies from the unweighted fit of the whole recording.

Printed: one row per cell, then, for blocks and for chained, the rank correlation with forward
over the cells and how often it names the forward winner (cells where forward is within ±1 %
left out).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import model_choice as mc  # noqa: E402

from magcal.fit import fit_calibration, geometric, holdout, pipeline  # noqa: E402
from magcal.fit.failure import FitFailure  # noqa: E402

TIE = 0.01


def _fits(train):
    """(samples, sphere, fullest determined ellipsoid (fit, kept mask)) as fit's "auto" has
    them, or None where the coverage determines no ellipsoid."""
    m, _ = pipeline._samples(train)
    start = pipeline._robust_sphere(m, pipeline.DEFAULT_MAX_CONDITION)
    if isinstance(start, FitFailure):
        return None
    limits = pipeline._Limits(True, pipeline._outliers.DEFAULT_ALPHA, pipeline.DEFAULT_MAX_ELLIPSOID_CONDITION,
                              pipeline.DEFAULT_MAX_SHAPE_SIGMA)
    candidates, _ = pipeline._candidates(m, "auto", *start, limits, [], {})
    kind = next((k for k in ("full", "diagonal") if k in candidates), None)
    return None if kind is None else (m, candidates["sphere"][0], candidates[kind])


def _blocks_ratio(m, sphere, g, keep) -> float:
    """Balanced ÷ unweighted held-out spread on the training part's own time blocks (all their
    samples, the blocks both refits reach), as ``holdout`` judges the balance; nan where the
    part is too short for blocks."""
    edges = holdout.block_edges(len(m))
    if np.min(np.add.reduceat(keep, edges[:-1])) < holdout.MIN_BLOCK:
        return float("nan")
    tests, _ = holdout._tests(m, keep, edges, sphere.offset_ut)
    at_whole = geometric.residual_jacobian(g.theta, m, g.kind)
    plain = holdout._score(m, g, keep, tests, edges, False, at_whole)
    weighted = holdout._score(m, g, keep, tests, edges, True, at_whole)
    both = np.array([p is not None and w is not None for p, w in zip(plain, weighted)])
    if not both.any():
        return float("nan")
    return holdout._over(weighted, "all", both) / holdout._over(plain, "all", both)


def _chained_ratio(m, g, keep) -> float:
    """Balanced ÷ unweighted spread forward-chained over the training part's time blocks: both
    refitted on the blocks before each block and judged on it (all its kept samples); the
    geometric mean over the blocks both refits reach, nan where none does."""
    edges = holdout.block_edges(len(m))
    at_whole = geometric.residual_jacobian(g.theta, m, g.kind)
    logs = []
    for j in range(1, len(edges) - 1):
        past, block = keep.copy(), keep.copy()
        past[edges[j]:] = False
        block[: edges[j]] = False
        block[edges[j + 1]:] = False
        if block.sum() < holdout.MIN_BLOCK:
            continue
        plain, weighted = (holdout._refit(m, past, g, bal, at_whole) for bal in (False, True))
        if not isinstance(plain, FitFailure) and not isinstance(weighted, FitFailure):
            logs.append(np.log(holdout.spread(m[block], weighted, g.kind) / holdout.spread(m[block], plain, g.kind)))
    return float(np.exp(np.mean(logs))) if logs else float("nan")


def _spread(test, g) -> float:
    h = np.linalg.norm((test - g.offset_ut) @ g.soft_iron.T, axis=1)
    return float(np.std(h) / np.mean(h))


def cell(whole_offset_ut, train, test) -> dict | None:
    fits = _fits(train)
    if fits is None:
        return None
    m, sphere, (g, keep) = fits
    balanced = pipeline._balanced(m[keep], g, "directions", [])[0]
    return {"kind": g.kind, "forward": _spread(test, balanced) / _spread(test, g),
            "blocks": _blocks_ratio(m, sphere, g, keep), "chained": _chained_ratio(m, g, keep),
            "moved_ut": float(np.linalg.norm(balanced.offset_ut - g.offset_ut)),
            "from_whole_ut": float(np.linalg.norm(g.offset_ut - whole_offset_ut))}


def _ranks(x: np.ndarray) -> np.ndarray:
    r = np.empty(len(x))
    r[np.argsort(x)] = np.arange(len(x))
    return r


def summary(rows: list[dict], verdict: str = "blocks") -> str:
    f = np.array([r["forward"] for r in rows])
    b = np.array([r[verdict] for r in rows])
    ok = np.isfinite(f) & np.isfinite(b)
    rho = float(np.corrcoef(_ranks(f[ok]), _ranks(b[ok]))[0, 1]) if ok.sum() > 2 else float("nan")
    decided = ok & (np.abs(f - 1.0) > TIE)
    agree = int(np.sum(np.sign(f[decided] - 1.0) == np.sign(b[decided] - 1.0)))
    helps = int(np.sum(f[ok] < 1.0 - TIE))
    hurts = int(np.sum(f[ok] > 1.0 + TIE))
    return (f"{int(ok.sum())} cells: rank correlation forward ~ {verdict} {rho:+.2f}; {verdict} names the forward"
            f" winner in {agree} of {int(decided.sum())} cells decided beyond ±{100 * TIE:.0f} %; the balance helps"
            f" forward in {helps}, hurts in {hurts}")


def run(recs: dict, splits) -> list[dict]:
    print("| recording | split | ellipsoid | forward bal/plain | blocks bal/plain | chained bal/plain |"
          " offset moved by balance µT | unweighted from whole µT |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for name, m in recs.items():
        whole = fit_calibration(m, model="ellipsoid", balance="none")
        if not whole:
            continue
        for frac in splits:
            k = int(len(m) * frac)
            c = cell(np.asarray(whole.calibration.offset_ut), m[:k], m[k:])
            if c is None:
                continue
            rows.append(c)
            print(f"| {name} | {frac:.0%} | {c['kind']} | {c['forward']:.3f} | {c['blocks']:.3f} | {c['chained']:.3f} | "
                  f"{c['moved_ut']:.2f} | {c['from_whole_ut']:.2f} |", flush=True)
    print("\n" + summary(rows) + "\n" + summary(rows, "chained"))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--splits", default=",".join(str(f) for f in mc.SPLITS))
    ap.add_argument("--only", action="append", help="only this recording (repeatable)")
    a = ap.parse_args(argv)
    recs = {k: v for k, v in mc.recordings().items()
            if k not in mc.SEALED and not k.startswith("tests/data") and (not a.only or k in a.only)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run(recs, tuple(float(x) for x in a.splits.split(",")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
