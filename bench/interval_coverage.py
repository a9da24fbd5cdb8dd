"""Do the stated 95 % intervals cover the change between a recording's independent halves?

    MAGCAL_REAL_DATA=… python bench/interval_coverage.py [--sealed] [--only NAME] [--no-tracker]

Every real recording ``bench/model_choice.py`` loads but the excerpts in tests/data (copies of
recordings already in the set; the public recordings kept there whole are in), with its own times (the sealed ones of docs/sealed.md only with
``--sealed``, printed apart), is cut in two at its middle sample. Each half is calibrated on
its own, and for each parameter θ with a stated 1σ the pair is *covered* when

    |θ₁ − θ₂| ≤ 1.96 · √(σ₁² + σ₂²)

(the two halves are independent, so under the stated σ the difference is N(0, σ₁² + σ₂²) and
95 % of pairs should pass). Target (issue 41.3): ≥ 90 % of (recording, parameter) pairs.

* fit     — ``fit_calibration(half, model="auto")``, what ``magcal fit`` does: the offset (3), the
            field and the soft-iron diagonal (3). A diagonal that both halves fixed at 1 (a
            sphere on each) states nothing and is left out; a sphere's 0 σ beside an ellipsoid
            counts (the sphere claimed the axis gains are exact).
* tracker — a fresh ``Tracker`` fed each half, its final calibration as ``magcal track``
            reports it (``tracker_check.checked`` with the half: a model fit's gates accept on
            memory and on the half, each σ at least fit's there): the same seven parameters,
            two spheres' diagonals left out as for fit; beside it, the tracker's offset σ over
            fit's on the same half (≥ 1 by construction).

Per row: the change in units of its stated 2-sided 95 % half-width (≤ 1 covered), so a row
shows how far short an interval falls, not only whether it does.
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
import real_recordings as rr  # noqa: E402

from magcal.fit import fit_calibration  # noqa: E402
from magcal.fit.tracker import Tracker  # noqa: E402
from magcal.fit.tracker_check import checked  # noqa: E402

Z95 = 1.96
NAMES = ("offset_x", "offset_y", "offset_z", "field", "W_xx", "W_yy", "W_zz")


def recordings() -> dict:
    """name → (t_s, (n, 3) µT), as model_choice loads them but with their times (the tracker's
    refit pace is in sample time)."""
    recs = dict(rr.available(rr.RAW_LOADERS))
    for f in ("putty_00.log", "putty_05.log"):
        try:
            recs[f"lsm9ds1_pesboard {f}"] = mc._pesboard(f)
        except (OSError, ValueError):
            pass
    recs.update(mc._flight_logs())  # tests/data's excerpts are left out: each is a copy of one of these
    recs.update(mc._public())  # …but for the public recordings kept there whole
    out = {}
    for k, (t, m) in recs.items():
        t, m = np.asarray(t, float), np.asarray(m, float)
        ok = np.all(np.isfinite(m), axis=1) & np.isfinite(t)
        out[k] = (t[ok], m[ok])
    return out


def fit_params(m) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(θ (7), σ (7), model) of ``fit`` on m, or None when it refuses."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = fit_calibration(m, model="auto")
    if not r:
        return None
    c, u = r.calibration, r.uncertainty
    th = np.r_[c.offset_ut, c.field_ut, np.diag(np.asarray(c.soft_iron))]
    sg = np.r_[u["offset_ut"], u["field_ut"], np.diag(np.asarray(u["soft_iron"]))]
    return th, sg, r.model


def tracker_params(t, m) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(θ (7), σ (7), model) of a fresh tracker's final calibration on (t, m) as ``magcal track``
    reports it (``tracker_check.checked``: a model fit's gates accept, σ at least fit's)."""
    tr = Tracker()
    tr.add_many(m, t)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        e = checked(tr, m)
    if e is None:
        return None
    c = e.calibration
    th = np.r_[c.offset_ut, c.field_ut, np.diag(np.asarray(c.soft_iron))]
    sg = np.r_[e.offset_sigma_ut, e.field_sigma_ut, np.diag(np.asarray(e.soft_iron_sigma))]
    return th, sg, e.model + (f" (not {e.refused_model})" if e.refused_model else "")


def ratios(a, b, sphere_both: bool) -> np.ndarray:
    """|θ₁ − θ₂| / (1.96 √(σ₁² + σ₂²)) per parameter; NaN where nothing was stated."""
    (t1, s1, _), (t2, s2, _) = a, b
    half = Z95 * np.sqrt(s1**2 + s2**2)
    d = np.abs(t1 - t2)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(half > 0, d / half, np.where(d > 1e-9, np.inf, np.nan))
    if sphere_both and len(r) == 7:
        r[4:] = np.nan
    return r


def score(name, t, m, tracker: bool) -> dict:
    k = len(m) // 2
    out = {"name": name, "n": len(m)}
    f1, f2 = fit_params(m[:k]), fit_params(m[k:])
    if f1 and f2:
        out["fit"] = ratios(f1, f2, f1[2] == "sphere" and f2[2] == "sphere")
        out["fit_models"] = f"{f1[2]} / {f2[2]}"
    else:
        out["fit_models"] = "refused on " + " and ".join(h for h, f in (("1st", f1), ("2nd", f2)) if not f)
    if tracker:
        r1, r2 = tracker_params(t[:k], m[:k]), tracker_params(t[k:], m[k:])
        if r1 and r2:
            out["tracker"] = ratios(r1, r2, r1[2] == "sphere" and r2[2] == "sphere")
            out["tracker_models"] = f"{r1[2]} / {r2[2]}"
            out["tracker_sigma"] = np.sqrt(r1[1][:3] ** 2 + r2[1][:3] ** 2)
            out["fit_sigma"] = (np.sqrt(f1[1][:3] ** 2 + f2[1][:3] ** 2) if f1 and f2 else None)
        else:
            out["tracker_models"] = "no estimate"
    return out


def _fmt(r) -> str:
    return "—" if r is None else " ".join("·" if not np.isfinite(v) and np.isnan(v) else f"{v:.2f}" for v in r)


def summary(rows, key: str) -> str:
    vals = np.concatenate([r[key][np.isfinite(r[key]) | np.isinf(r[key])] for r in rows if key in r] or [np.zeros(0)])
    vals = vals[~np.isnan(vals)]
    if not len(vals):
        return f"{key}: no pairs"
    cov = float(np.mean(vals <= 1.0))
    per = {}
    for r in rows:
        if key in r:
            for nm, v in zip(NAMES, r[key]):
                if not np.isnan(v):
                    per.setdefault(nm[:6] if nm.startswith("offset") else ("W_ii" if nm.startswith("W") else nm), []).append(v <= 1.0)
    parts = ", ".join(f"{k} {100 * np.mean(v):.0f} % of {len(v)}" for k, v in per.items())
    return (f"{key}: {int(np.sum(vals <= 1.0))}/{len(vals)} pairs covered = {100 * cov:.0f} % (target ≥ 90 %); "
            f"median ratio {np.median(vals):.2f}; {parts}")


def run(recs: dict, tracker: bool) -> list[dict]:
    print("| recording | n | fit models (halves) | fit: |Δ|/95 % half-width (ox oy oz F Wxx Wyy Wzz) | "
          "tracker models | tracker: |Δ|/95 % half-width (ox oy oz F Wxx Wyy Wzz) | tracker σ / fit σ (offset) |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for name, (t, m) in recs.items():
        r = score(name, t, m, tracker)
        rows.append(r)
        sig = (" ".join(f"{a / b:.2f}" for a, b in zip(r["tracker_sigma"], r["fit_sigma"]))
               if r.get("fit_sigma") is not None and "tracker_sigma" in r else "—")
        print(f"| {name} | {r['n']} | {r['fit_models']} | {_fmt(r.get('fit'))} | {r.get('tracker_models', '—')} | "
              f"{_fmt(r.get('tracker'))} | {sig} |", flush=True)
    print()
    print(summary(rows, "fit"))
    if tracker:
        print(summary(rows, "tracker"))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sealed", action="store_true", help="only the sealed recordings of docs/sealed.md")
    ap.add_argument("--only", action="append", help="only this recording (repeatable)")
    ap.add_argument("--no-tracker", action="store_true")
    a = ap.parse_args(argv)
    recs = {k: v for k, v in recordings().items() if (k in mc.SEALED) == a.sealed and (not a.only or k in a.only)}
    run(recs, not a.no_tracker)
    return 0


if __name__ == "__main__":
    sys.exit(main())
