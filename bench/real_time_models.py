"""Issue-5 follow-up: do models in which the calibration changes with time beat the constant one
on the held-out half of the real recordings?

    python3 bench/real_time_models.py [--degrees 2,4,8,16]     (≈ 1 min)

The fit half of a hand-held recording wanders (docs/notebook/bench-history.md): an offset that moves, or — when
the board is carried through a non-uniform indoor field — a field magnitude that changes with
position. Each rule below is decided from the fit half only and judged like bench/real_data.py
(spread of |calibrated field| on the held-out half, %), against MotionCal on the same splits:

* ``radius(t)``: |W(m − o)| = R(t), R a Legendre polynomial of degree D in time; the constant
  o and W are kept for the held-out half (the field-magnitude change is a nuisance);
* ``offset(t)``: |W(m − o(t))| = R, o(t) = o + Legendre degrees 1…D; o (the mean) is kept;
* ``block median``: ellipsoids fitted to K contiguous stretches of the fit half, the element-wise
  median of their offsets and (det-normalised) matrices kept — robust to one odd stretch.

Each starts from magcal's own fit (``magcal.fit.fit``: its outliers removed, its direction
weights), so the constant model with D = 0 reproduces the magcal column of real_data.py.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
from numpy.polynomial import legendre
from scipy.optimize import least_squares

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, ".."))

from real_data import MOTIONCAL, load_all, spread_pct  # noqa: E402

from magcal.fit import fit_calibration  # noqa: E402
from magcal.fit.direction_weights import direction_weights  # noqa: E402


def _unpack(p):
    o = p[:3]
    a, b, d, e, g = p[3:8]
    return o, np.array([[a, d, e], [d, b, g], [e, g, 3.0 - a - b]]), p[8:]  # trace fixed: no scale freedom


def time_varying(m, degree: int, kind: str):
    """(offset, matrix) of an ellipsoid whose radius (kind "radius") or offset ("offset")
    follows a degree-``degree`` Legendre polynomial in time over ``m`` (time order)."""
    r = fit_calibration(m, model="ellipsoid")
    c = r.calibration
    keep = np.ones(len(m), bool)
    keep[list(r.outliers)] = False
    m = m[keep]
    p_t = legendre.legvander(np.linspace(-1.0, 1.0, len(m)), degree)
    w0 = np.asarray(c.soft_iron)
    w0 = 3.0 * (w0 + w0.T) / np.trace(w0 + w0.T)
    h = (m - c.offset_ut) @ w0.T
    n = np.linalg.norm(h, axis=1)
    w = np.sqrt(direction_weights(h))
    extra = degree + 1 if kind == "radius" else 1 + 3 * degree
    q0 = np.zeros(extra)
    q0[0] = n.mean()
    p0 = np.r_[c.offset_ut, w0[0, 0], w0[1, 1], w0[0, 1], w0[0, 2], w0[1, 2], q0]

    def residual(p):
        o, wm, q = _unpack(p)
        if kind == "radius":
            return w * (np.linalg.norm((m - o) @ wm.T, axis=1) - p_t @ q)
        o_t = o + p_t[:, 1:] @ q[1:].reshape(degree, 3) if degree else o
        return w * (np.linalg.norm(np.einsum("ij,nj->ni", wm, m - o_t), axis=1) - q[0])

    o, wm, _ = _unpack(least_squares(residual, p0, method="lm").x)
    return o, wm


def block_median(m, k: int):
    edges = np.linspace(0, len(m), k + 1).astype(int)
    offs, mats = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        r = fit_calibration(m[a:b], model="ellipsoid")
        if r:
            w = np.asarray(r.calibration.soft_iron)
            offs.append(r.calibration.offset_ut)
            mats.append(w / np.cbrt(np.linalg.det(w)))
    return np.median(offs, axis=0), np.median(mats, axis=0)


def row(label, fn, data) -> str:
    out = []
    for name, (m, _) in data.items():
        half = len(m) // 2
        out.append(spread_pct(m[half:], *fn(m[:half])))
    wins = sum(s <= MOTIONCAL[n] + 5e-4 for s, n in zip(out, data))
    return f"| {label} | " + " | ".join(f"{s:.3f}" for s in out) + f" | {wins} of {len(out)} |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--degrees", default="2,4,8,16")
    args = ap.parse_args(argv)
    degrees = [int(d) for d in args.degrees.split(",")]
    data = load_all()
    print("| rule | " + " | ".join(data) + " | no worse than MotionCal |")
    print("|---|" + "---|" * (len(data) + 1))
    print("| MotionCal | " + " | ".join(f"{MOTIONCAL[n]:.2f}" for n in data) + " | |")
    print(row("constant (magcal, refitted here)", lambda m: time_varying(m, 0, "radius"), data), flush=True)
    for kind in ("radius", "offset"):
        for d in degrees:
            print(row(f"{kind}(t), degree {d}", lambda m, d=d, kind=kind: time_varying(m, d, kind), data), flush=True)
    for k in (2, 3, 4):
        print(row(f"block median, {k} stretches", lambda m, k=k: block_median(m, k), data), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
