"""Are `diagnose`'s findings borne out by the recording's own halves? (issue 41: "no `diagnose`
finding contradicted by its own recording's independent halves").

    MAGCAL_REAL_DATA=… python bench/claims_halves.py [--sealed] [--only NAME] [--max-samples N] [--json FILE]

Each real recording (the set of bench/interval_coverage.py; the sealed ones of docs/sealed.md only
with ``--sealed``) is diagnosed whole and each half in time on its own, as a user would run
`magcal diagnose` on them. A recording longer than ``--max-samples`` keeps evenly spaced samples
over its whole span (the same samples for the whole and its halves). Each finding of the whole is
then put beside the halves:

- **supported**: a half reports the same effect (a channel term on the same channel; a line within
  2 % of its frequency; a hard-iron step or soft-iron change by the half that holds its time);
- **contradicted**: both halves report a channel term (a logged channel, or the drift in time)
  and their coefficients differ beyond their own stated covariances, χ² p < ``LEVEL`` — the two
  halves' statements cannot both hold, so the whole's cannot be trusted either; or the half that
  holds a change point's time fits and reports no change of that kind while the other half does;
- soft iron carries no interval in the JSON: its gain spread is printed for the whole and each
  half, for the reader, and counted as supported when a half finds soft iron too.

A finding no half reports is **unsupported**: not a contradiction (a half has half the samples,
and a finding near the limit of detection can vanish in both), but worth reading. Outliers are
not checked (they are samples, not a claim about the sensor). The figure is the count of
contradicted findings: the target is none.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402

import interval_coverage as ic  # noqa: E402
import model_choice as mc  # noqa: E402
from magcal.core.errors import MagcalError  # noqa: E402
from magcal.core.series import Series  # noqa: E402
from magcal.diagnose import diagnose  # noqa: E402
from magcal.fit.tails import chi2_sf  # noqa: E402

LEVEL = 0.01
CHANGES = ("hard_iron_step", "soft_iron_change")
SKIPPED = ("outliers",)


def findings(t: np.ndarray, m: np.ndarray) -> list[dict] | str:
    """diagnose's findings on these samples, or why it refused."""
    try:
        return diagnose(Series(t_s=t, field_ut=m)).to_dict()["findings"]
    except MagcalError as exc:
        return f"{type(exc).__name__}: {str(exc)[:100]}"


def key(f: dict) -> tuple:
    """(effect, channel) of a finding; lines by frequency are matched apart."""
    return f["effect"], f.get("where", {}).get("channel")


def coef_cov(f: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """A channel term's coefficient and its stated covariance (a finding states them in its
    evidence, beside the test that estimated them), or None."""
    p = f.get("evidence", {})
    if "coef_cov_ut_per_unit" not in p:
        return None
    ci = np.asarray(p["coef_ci95_ut_per_unit"], float)
    return ci.mean(axis=1), np.asarray(p["coef_cov_ut_per_unit"], float)


def same_line(f: dict, g: dict) -> bool:
    fa, fb = f.get("where", {}).get("frequency_hz"), g.get("where", {}).get("frequency_hz")
    return fa is not None and fb is not None and abs(fa - fb) <= 0.02 * fa


def matches(f: dict, half: list[dict]) -> list[dict]:
    if f["effect"] == "narrowband_line":
        return [g for g in half if g["effect"] == f["effect"] and same_line(f, g)]
    return [g for g in half if key(g) == key(f)]


def change_time(f: dict) -> float:
    return float(np.atleast_1d(f["params"].get("time_s", f["where"].get("time_s")))[0])


def judge_change(f: dict, halves: list, t_mid: float) -> str:
    """A change point: the half that holds its time should see it."""
    holder = halves[0] if change_time(f) < t_mid else halves[1]
    if isinstance(holder, str):
        return "untestable"
    return "supported" if matches(f, holder) else "unsupported"


def judge_term(f: dict, halves: list) -> tuple[str, float | None]:
    """(verdict, χ² p of the halves' difference where both state the coefficient)."""
    seen = [matches(f, h) if not isinstance(h, str) else [] for h in halves]
    if not any(seen):
        return "unsupported", None
    both = [coef_cov(s[0]) for s in seen if s]
    if len(both) < 2 or any(b is None for b in both):
        return "supported", None
    (a, ca), (b, cb) = both
    d = a - b
    try:
        chi2 = float(d @ np.linalg.solve(ca + cb, d))
    except np.linalg.LinAlgError:
        return "supported", None
    p = float(chi2_sf(chi2, len(d)))
    return ("contradicted" if p < LEVEL else "supported"), p


def spread(fs) -> str:
    if isinstance(fs, str):
        return "refused"
    s = [f["where"]["gain_spread_pct"] for f in fs if f["effect"] == "soft_iron"]
    return f"{s[0]:.1f} %" if s else "none"


def one(name: str, t: np.ndarray, m: np.ndarray, max_n: int) -> dict:
    if len(t) > max_n:
        keep = np.unique(np.linspace(0, len(t) - 1, max_n).astype(int))
        t, m = t[keep], m[keep]
    whole = findings(t, m)
    if isinstance(whole, str):
        return {"recording": name, "status": whole}
    h = len(t) // 2
    halves = [findings(t[:h], m[:h]), findings(t[h:], m[h:])]
    rows = []
    for f in whole:
        if f["effect"] in SKIPPED:
            continue
        if f["effect"] in CHANGES:
            verdict, p = judge_change(f, halves, float(t[h])), None
        else:
            verdict, p = judge_term(f, halves)
        rows.append({"effect": f["effect"], "channel": f.get("where", {}).get("channel"),
                     "frequency_hz": f.get("where", {}).get("frequency_hz"), "verdict": verdict, "p": p})
    return {"recording": name, "status": "ok", "samples": len(t), "findings": rows,
            "soft_iron_spread": [spread(whole), spread(halves[0]), spread(halves[1])],
            "halves_refused": [x for x in halves if isinstance(x, str)]}


def show(r: dict) -> None:
    if r["status"] != "ok":
        print(f"{r['recording']:<44} not diagnosed: {r['status']}", flush=True)
        return
    said = ", ".join(f"{x['effect']}{'(' + x['channel'] + ')' if x['channel'] else ''}"
                     f"{' %.2f Hz' % x['frequency_hz'] if x['effect'] == 'narrowband_line' else ''}: {x['verdict']}"
                     + (f" p={x['p']:.2g}" if x["p"] is not None else "") for x in r["findings"])
    print(f"{r['recording']:<44} n={r['samples']:<6} soft iron whole/halves {'/'.join(r['soft_iron_spread'])}; "
          f"{said or 'no finding'}" + (f"; a half refused: {r['halves_refused']}" if r["halves_refused"] else ""), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sealed", action="store_true", help="only the sealed recordings of docs/sealed.md")
    ap.add_argument("--only", default="", help="only recordings whose name holds this")
    ap.add_argument("--max-samples", type=int, default=12000, help="evenly spaced samples kept of a longer recording")
    ap.add_argument("--json", help="write every recording's verdicts here")
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    recs = {k: v for k, v in ic.recordings().items() if (k in mc.SEALED) == a.sealed and a.only in k}
    out = []
    for name, (t, m) in recs.items():
        out.append(one(name, t, m, a.max_samples))
        show(out[-1])
    rows = [x for r in out if r["status"] == "ok" for x in r["findings"]]
    count = {v: sum(x["verdict"] == v for x in rows) for v in ("supported", "unsupported", "contradicted", "untestable")}
    print(f"{len(rows)} findings on {sum(r['status'] == 'ok' for r in out)} recordings: {count}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
