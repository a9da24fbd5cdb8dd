"""End-to-end check of the locate step: effects outside the catalogue injected into simulated
and real raw recordings, judged on what `diagnose` says and where.

    python bench/locate_eval.py [--quick] [--sizes 2,4,10] [--seed N] [--control-windows K] [--json out.json]

Each case is a recording (simulated, or a real raw recording of ../shared/data/real via
bench/real_recordings.py) with one effect added to its raw samples at 2–10× the recording's
own floor (the RMS radial residual of a plain ellipsoid), and the same recording without it as
a control. For every case it prints whether `diagnose` located the effect (time within ±1 s or
5 % of the span, frequency within 2 %, the right channel or axis), named it (the effect's name
or `unexplained_structure`), claimed something specific on a control, and whether the returned
calibration is no worse than a plain ellipsoid on the held-out last fifth.

Controls: each recording as it is, and ``--control-windows`` K disjoint windows of each real
recording (each at least ``WINDOW_MIN_S`` long and ``WINDOW_MIN_N`` samples; fewer where the
recording is too short), so the false-claim rate on controls is measured on over a hundred of
them. The windows are pieces of the same recordings, not independent recordings: the output
says how many controls came from windows. ``--seed`` sets the placements (say which seeds a
change was developed on, and measure it on another).

Lines a recording carries before anything is injected (``CARRIED_LINE_EVIDENCE``: the recordings
whose raw spectrum was shown to hold them, and the script that shows it) are part of that
recording: a `narrowband_line` claim within 2 % (or two Welch bins) of one of them, found on the
un-injected recording by that script's spectrum, is counted neither false nor as naming or
locating an injected effect (unless it also sits at the injected frequency).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass, field

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import real_recordings  # noqa: E402
from apex5_lines import NPERSEG, carried_lines  # noqa: E402

from magcal.core.errors import InputError  # noqa: E402
from magcal.core.series import Series  # noqa: E402
from magcal.diagnose import diagnose  # noqa: E402
from magcal.fit import fit_calibration  # noqa: E402
from magcal.sim.physics import Motion, Physics, Scenario  # noqa: E402

MAX_N = 6000
WINDOW_MIN_S = 14.0  # a control window shorter than this is not taken (the step search needs 12 s)
WINDOW_MIN_N = 400
MIN_HUM_CYCLES = 20.0
# recordings with lines in their raw spectrum before any injection, and the evidence for them
CARRIED_LINE_EVIDENCE = {
    "betaflight_apex5_tpu_02": "bench/apex5_lines.py",
    "betaflight_apex5_tpu_03": "bench/apex5_lines.py",
}


@dataclass
class Case:
    name: str
    effect: str  # what should be named ("" for a control)
    series: Series
    where: dict = field(default_factory=dict)  # the truth: time_s (instant or stretch), frequency_hz, channel, axis


def floor_ut(m: np.ndarray) -> float:
    r = fit_calibration(m, model="ellipsoid")
    return float(r.rms_ut) if r else 1.0


def base_recordings(quick: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for seed, motion in ((11, Motion("sphere", period_s=20.0)), (12, Motion("tilt", max_tilt_deg=50.0))):
        run = Scenario(physics=Physics(hard_iron_ut=(21.0, -33.0, 8.0), noise_ut=0.3), motion=motion, seed=seed).simulate(4000, 50.0)
        out[f"sim_{motion.kind}_{seed}"] = (run.series.t_s, run.series.field_ut)
    out.update(real_recordings.raw_in_ut(quick, MAX_N))
    return out


def control_windows(name: str, t: np.ndarray, m: np.ndarray, k: int) -> list[Case]:
    """Up to ``k`` disjoint, equal windows of one recording as further controls."""
    for parts in range(k, 0, -1):
        edges = np.linspace(t[0], t[-1], parts + 1)
        cut = np.searchsorted(t, edges)
        if (edges[1] - edges[0]) >= WINDOW_MIN_S and np.min(np.diff(cut)) >= WINDOW_MIN_N:
            return [Case(f"{name}/control_w{i}", "", _s(t[a:b] - t[a], m[a:b])) for i, (a, b) in
                    enumerate(zip(cut[:-1], cut[1:]))] if parts > 1 else []
    return []


def hum_frequency_hz(t: np.ndarray) -> float:
    """Where mains hum lands after the sample clock aliases it: 50 Hz, else 60 Hz, else (a clock
    that is a multiple of both) a seventh of the rate. An alias under ``MIN_HUM_CYCLES`` cycles
    over the span is no line but an offset (a clock at a multiple of the mains frequency sees the
    hum as a constant), so it is not used."""
    rate = 1.0 / float(np.median(np.diff(t)))
    for mains in (50.0, 60.0):
        f = abs(mains - rate * round(mains / rate))
        if f * float(t[-1] - t[0]) >= MIN_HUM_CYCLES:
            return f
    return rate / 7.3


def inject(name: str, t: np.ndarray, m: np.ndarray, rng: np.random.Generator, size: float) -> list[Case]:
    """One case per effect at ``size`` × the recording's floor, placed at random."""
    fl = floor_ut(m)
    span = t[-1] - t[0]
    centre = fit_calibration(m, model="sphere")
    b = centre.calibration.offset_ut if centre else m.mean(0)
    tau = float(t[0] + span * rng.uniform(0.3, 0.7))
    after = t >= tau
    cases = []
    d = rng.standard_normal(3)
    d *= size * fl / np.linalg.norm(d)
    cases.append(Case(f"{name}/step", "hard_iron_step", _s(t, m + np.outer(after, d)), {"time_s": tau}))
    gain = 1.0 + size * fl / 50.0
    m2 = m.copy()
    m2[after, 0] = b[0] + gain * (m[after, 0] - b[0])
    cases.append(Case(f"{name}/soft_change", "soft_iron_change", _s(t, m2), {"time_s": tau}))
    f_alias = hum_frequency_hz(t)
    axis = int(rng.integers(3))
    hum = np.zeros_like(m)
    hum[:, axis] = size * fl * np.sqrt(2) * np.cos(2 * np.pi * f_alias * t + rng.uniform(0, 6.28))
    cases.append(Case(f"{name}/hum", "narrowband_line", _s(t, m + hum), {"frequency_hz": f_alias, "axis": "xyz"[axis]}))
    temp = 22.5 + 7.5 * np.sin(2 * np.pi * t / max(span / 1.5, 1.0))
    g = size * fl / 50.0 / 7.5
    cases.append(Case(f"{name}/temp_gain", "temperature_gain",
                      _s(t, b + (1 + g * (temp - 22.5))[:, None] * (m - b), {"temp_c": temp}), {"channel": "temp_c"}))
    cases.extend(_faults(name, t, m, rng))
    cases.extend(_lagged(name, t, m, rng, size * fl))
    return cases


def _lagged(name, t, m, rng, amp_ut) -> list[Case]:
    on = (np.sin(2 * np.pi * t / 9.0 + rng.uniform(0, 6)) > 0.2).astype(float)
    cur = 8.0 * on + 0.2 * rng.standard_normal(len(t))
    tau_s = float(rng.uniform(0.3, 1.0))
    dt = np.diff(t, prepend=t[0])
    lagged = np.zeros_like(cur)
    for i in range(1, len(t)):
        a = np.exp(-dt[i] / tau_s)
        lagged[i] = a * lagged[i - 1] + (1 - a) * cur[i]
    beta = rng.standard_normal(3)
    beta *= amp_ut / 8.0 / np.linalg.norm(beta)
    return [Case(f"{name}/lagged_current", "lagged_channel", _s(t, m + np.outer(lagged, beta), {"current_a": cur}),
                 {"channel": "current_a", "lag_s": tau_s, "coef_ut_per_unit": beta})]


def _faults(name, t, m, rng) -> list[Case]:
    n = len(t)
    rate = 1.0 / np.median(np.diff(t))
    length = int(rng.uniform(2, 8) * rate)
    i0 = int(rng.integers(n // 5, max(n // 5 + 1, n - length - n // 10)))
    stuck = m.copy()
    axis = int(rng.integers(3))
    stuck[i0 : i0 + length, axis] = stuck[i0, axis]
    swap = m.copy()
    swap[i0 : i0 + length, [0, 1]] = swap[i0 : i0 + length, [1, 0]]
    lo, hi = np.percentile(m, [3, 97], axis=0)
    stretch = [float(t[i0]), float(t[min(i0 + length, n - 1)])]
    return [
        Case(f"{name}/stuck", "stuck_axis", _s(t, stuck), {"time_s": stretch, "axis": "xyz"[axis]}),
        Case(f"{name}/swap", "axis_swap", _s(t, swap), {"time_s": stretch}),
        Case(f"{name}/rail", "saturation", _s(t, np.clip(m, lo, hi)), {}),
    ]


def _s(t, m, chans=None) -> Series:
    return Series(t_s=t, field_ut=m, channels=chans or {})


def located_right(item: dict, case: Case, span: float) -> bool:
    where, truth = item.get("where", {}), case.where
    if "time_s" in truth:
        if not where.get("time_s"):
            return False
        tol = max(1.0, 0.05 * span)
        want = np.atleast_1d(truth["time_s"]).astype(float)
        got = np.asarray(where["time_s"], float).reshape(-1)
        if not np.any(np.abs(got[:, None] - want[None, :]) <= tol):
            return False
    if "frequency_hz" in truth:
        f = where.get("frequency_hz")
        if f is None or abs(np.atleast_1d(f)[0] - truth["frequency_hz"]) > 0.02 * truth["frequency_hz"]:
            return False
    if "channel" in truth and where.get("channel") != truth["channel"]:
        return False
    return True


def recording_lines(name: str, t: np.ndarray, m: np.ndarray) -> list[float]:
    """The lines the un-injected recording carries (Hz), for recordings with the evidence."""
    return carried_lines(t, m) if name in CARRIED_LINE_EVIDENCE else []


def is_carried(item: dict, case: Case, carried: list[float]) -> bool:
    """A `narrowband_line` claim at a line the recording carried before injection (and not at
    the injected frequency)."""
    f = item.get("where", {}).get("frequency_hz")
    if item.get("effect") != "narrowband_line" or f is None or not carried:
        return False
    f = float(np.atleast_1d(f)[0])
    truth = case.where.get("frequency_hz")
    if truth is not None and abs(f - truth) <= 0.02 * truth:
        return False
    rate = 1.0 / float(np.median(np.diff(case.series.t_s)))
    return any(abs(f - c) <= max(0.02 * c, 2.0 * rate / NPERSEG) for c in carried)


def judge_case(case: Case, carried: list[float] | None = None) -> dict:
    try:
        d = diagnose(case.series).to_dict()
    except InputError as exc:
        return {"case": case.name, "control": not case.effect, "named": False, "located": False,
                "said": [f"refused: {exc}"], "false_claims": [], "remainder": False}
    return judge(d, case, carried or [])


def judge(d: dict, case: Case, carried: list[float]) -> dict:
    """The verdict on one diagnosis; claims of lines the recording carried are set aside."""
    keep = [x for x in d["findings"] if not is_carried(x, case, carried)]
    items = [x for x in d["located"]["found"] + d["limits"] + keep if not is_carried(x, case, carried)]
    span = float(case.series.t_s[-1] - case.series.t_s[0])
    specific = [x for x in keep if x.get("evidence", {}).get("kind") in ("physics", "fault")]
    if not case.effect:
        return {"case": case.name, "control": True, "false_claims": [x["effect"] for x in specific],
                "remainder": any(x.get("effect") == "unexplained_structure" for x in d["limits"])}
    named = [x for x in items if x.get("effect") in (case.effect, "unexplained_structure")]
    return {"case": case.name, "control": False, "named": bool(named),
            "located": any(located_right(x, case, span) for x in named),
            "said": sorted({x.get("effect") for x in items if x.get("effect")}),
            "false_claims": [x["effect"] for x in specific if x["effect"] != case.effect],
            "false_where": [x.get("where", {}) for x in specific if x["effect"] != case.effect]} | lag_verdict(d, case)


def lag_verdict(d: dict, case: Case) -> dict:
    """For a lagged channel: the located term on that channel (the lagged one first) — its
    coefficient's error against the truth (as a share of the true size), whether the true size is
    inside its stated 95 % interval, and its lag's error (as a share of the true time constant)."""
    truth = case.where.get("coef_ut_per_unit")
    if truth is None:
        return {}
    on = [x for x in d["located"]["found"] if x.get("params", {}).get("channel") == case.where["channel"]
          and "coef_ut_per_unit" in x.get("params", {})]
    on.sort(key=lambda x: x.get("effect") != "lagged_channel")
    if not on:
        return {"lag": None}
    p, tb = on[0]["params"], np.asarray(truth)
    lo, hi = p.get("coef_magnitude_interval", [np.nan, np.nan])
    lag = on[0].get("where", {}).get("lag_s")
    return {"lag": {"effect": on[0]["effect"], "form": p.get("form"),
                    "coef_error": float(np.linalg.norm(np.asarray(p["coef_ut_per_unit"]) - tb) / np.linalg.norm(tb)),
                    "inside_95": bool(lo <= np.linalg.norm(tb) <= hi),
                    "lag_error": None if lag is None else float(abs(lag - case.where["lag_s"]) / case.where["lag_s"])}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="four real recordings, one size")
    ap.add_argument("--json", help="write every case's verdict here")
    ap.add_argument("--sizes", default="2,4,10", help="effect sizes, × the recording's floor (default 2,4,10)")
    ap.add_argument("--seed", type=int, default=2026, help="placements of the effects (default 2026)")
    ap.add_argument("--only", default="", help="only these effect cases, e.g. hum,step (default: every one)")
    ap.add_argument("--control-windows", type=int, default=0,
                    help="also take up to K disjoint windows of each real recording as controls (default 0)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    for name, (t, m) in base_recordings(args.quick).items():
        carried = recording_lines(name, t, m)
        rows.append(judge_case(Case(f"{name}/control", "", _s(t, m)), carried))
        if not name.startswith("sim_"):
            for case in control_windows(name, t, m, args.control_windows):
                rows.append(judge_case(case, carried))
                print(f"{case.name:50s} control   false {rows[-1]['false_claims']} remainder {rows[-1]['remainder']}",
                      flush=True)
        for size in ((4.0,) if args.quick else tuple(float(x) for x in args.sizes.split(","))):
            for case in inject(name, t, m, rng, size):
                if args.only and case.name.split("/")[1] not in args.only.split(","):
                    continue
                rows.append(judge_case(case, carried) | {"size": size})
                r = rows[-1]
                print(f"{r['case']:50s} x{size:<4} named {r['named']!s:5} located {r['located']!s:5} said {r['said']}"
                      + (f" lag {r['lag']}" if "lag" in r else ""), flush=True)
    summarise(rows)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


def summarise(rows: list[dict]) -> None:
    eff = [r for r in rows if not r["control"]]
    ctl = [r for r in rows if r["control"]]
    by = {}
    for r in eff:
        by.setdefault(r["case"].split("/")[1], []).append(r)
    for k, rs in sorted(by.items()):
        print(f"{k:16s} located {sum(r['located'] for r in rs)}/{len(rs)}  named {sum(r['named'] for r in rs)}/{len(rs)}  "
              f"false {sum(bool(r['false_claims']) for r in rs)}/{len(rs)}")
    print(f"effects: located {np.mean([r['located'] for r in eff]):.0%}, named {np.mean([r['named'] for r in eff]):.0%}, "
          f"specific false claims {np.mean([bool(r['false_claims']) for r in eff]):.0%} of {len(eff)}")
    summarise_lags([r for r in eff if "lag" in r])
    win = [r for r in ctl if "/control_w" in r["case"]]
    real = [r for r in ctl if not r["case"].startswith("sim_")]
    print(f"controls: false claims {sum(bool(r['false_claims']) for r in ctl)}/{len(ctl)} "
          f"({len(win)} of them disjoint windows of the real recordings), "
          f"remainder {sum(r['remainder'] for r in ctl)}/{len(ctl)}; real controls: false claims "
          f"{sum(bool(r['false_claims']) for r in real)}/{len(real)}, remainder {sum(r['remainder'] for r in real)}/{len(real)}")
    for r in ctl:
        if r["false_claims"]:
            print(f"  control {r['case']}: {r['false_claims']}")


def summarise_lags(rows: list[dict]) -> None:
    """The lagged channel's coefficient (within 20 %, truth inside its 95 % interval) and lag
    (within 30 %), over the lagged cases (a case with no term on the channel fails all three)."""
    if not rows:
        return
    got = [r["lag"] or {} for r in rows]
    coef = sum(g.get("coef_error", np.inf) <= 0.2 for g in got)
    inside = sum(bool(g.get("inside_95")) for g in got)
    lag = sum(g.get("lag_error") is not None and g["lag_error"] <= 0.3 for g in got)
    print(f"lagged channel: coefficient within 20 % {coef}/{len(rows)}, inside its 95 % interval {inside}/{len(rows)}, "
          f"lag within 30 % {lag}/{len(rows)}")


if __name__ == "__main__":
    raise SystemExit(main())
