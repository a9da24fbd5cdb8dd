"""Keeping a calibration: magcal's static fit and its tracker against MotionCal's real core.

Peer: PJRC MotionCal's own calibration core (``bench/tracking_peer.py`` says how it is driven
and where its figures are kept). MotionCal picks at random which buffered point to drop, so
every MotionCal figure here is the median over ``SEEDS`` seeds, per cell.

Recordings: the seven of ``bench/real_data.py``, every sample rounded to MotionCal's 0.1 µT
count for both sides (the peer only ever sees integer counts). The QMC5883L file is in raw
counts; it is scaled so its field is 50 µT (MotionCal refuses a field outside 22–67 µT).
Times: the hmc5883l files' own time column; fxos8700 10 Hz and qmc5883l 50 Hz as their
provenance states; the other three have no time and are fed at an assumed 50 Hz.

Static (70 cells): split points 30, 40, 50, 60, 70 % (fit on the part before, judge the part
after) and five contiguous folds (judge one fold, fit on the other four, concatenated in time
order) of each recording. Figure: held-out spread = std/mean of |calibrated field| (%).
magcal: ``fit_calibration(train, model="auto")`` (what ``magcal fit`` does). MotionCal: the calibration it
would send after the last training sample.

Online (each recording once, judged after each split point): the whole recording is fed in
time order; judged on the samples after the split.
  causal   — each sample calibrated with the calibration in force just before it;
  lagged   — with the calibration in force L = min(500, n/3) samples earlier (≈ 10 s at
             50 Hz): a tracker that chases the last samples' radial error loses here;
  snapshot — the calibration in force at every 100th sample, each judged on the whole judged
             part (mean over snapshots);
  floor    — the plain ML ellipsoid of the judged part itself (in-sample): a causal figure far
             below it would be fitting noise.

``--unseen``: the same tables on the nine other raw recordings of ``real_recordings.py`` (the
umich ICM-20948 and RM3100 pre-flight and flight logs, four Betaflight QMC5883L calibration
windows, the estibone RM3100), which nothing in magcal's fit or tracker was developed on; a cell
where ``fit`` refuses the training part (too little coverage) is counted, not averaged.

Run:  MAGCAL_REAL_DATA=… MAGCAL_MOTIONCAL_DRIVER=… python bench/tracking.py [--static] [--online]
      [--seeds K] [--only NAME] [--unseen] (both tables by default).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import tracking_peer as peer  # noqa: E402
from real_data import DATA, load_all  # noqa: E402

from magcal.fit import fit_calibration  # noqa: E402
from magcal.fit.tracker import Estimate, Tracker  # noqa: E402

SEEDS = 10
SPLITS = (0.3, 0.4, 0.5, 0.6, 0.7)
FOLDS = 5
SNAPSHOT_EVERY = 100
COUNT_UT = 0.1
RATE_HZ = {"fxos8700_mwrona": 10.0, "qmc5883l_tomisuarez": 50.0}
ASSUMED_RATE_HZ = 50.0
HMC_FILES = {"hmc5883l_sunsided full": "set-2_full-sphere_hmc5883l_mag.csv",
             "hmc5883l_sunsided tilt": "set-1_tilt-sphere_hmc5883l_mag.csv"}


# -- recordings ----------------------------------------------------------------------------
def recordings() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name → (t (n,) s, m (n, 3) µT on MotionCal's 0.1 µT grid), in time order."""
    out = {}
    for name, (m, _) in load_all().items():
        if name.startswith("qmc5883l"):
            m = m * (50.0 / np.median(np.linalg.norm(m - np.median(m, axis=0), axis=1)))
        if name in HMC_FILES:
            t = np.loadtxt(os.path.join(DATA, "hmc5883l_sunsided", HMC_FILES[name]),
                           usecols=0, skiprows=1, delimiter=",")
        else:
            t = np.arange(len(m)) / RATE_HZ.get(name, ASSUMED_RATE_HZ)
        out[name] = (t - t[0], COUNT_UT * np.round(m / COUNT_UT))
    return out


def unseen_recordings() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name → (t, m) of the raw recordings ``real_recordings.py`` holds beyond the seven (the
    umich, Betaflight and estibone files, ``RAW_LOADERS``): nothing here was developed on them.
    Rows with a non-finite value are dropped; every sample on MotionCal's 0.1 µT grid."""
    import real_recordings as rr

    out = {}
    more = {k: v for k, v in rr.RAW_LOADERS.items() if k not in rr.LOADERS}
    for name, (t, m) in rr.available(more).items():
        ok = np.all(np.isfinite(m), axis=1)
        t, m = t[ok], m[ok]
        out[name] = (t - t[0], COUNT_UT * np.round(m / COUNT_UT))
    return out


def joined_times(t: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Times for the samples ``idx`` fed back to back: a jump where idx skips becomes one
    ordinary sample interval."""
    dt = np.diff(t[idx])
    step = float(np.median(np.diff(t))) if len(t) > 1 else 0.02
    dt[np.diff(idx) != 1] = step
    return np.concatenate([[0.0], np.cumsum(dt)])


# -- figures -------------------------------------------------------------------------------
def spread_pct(m, offset, matrix) -> float:
    h = np.linalg.norm((m - offset) @ np.asarray(matrix).T, axis=1)
    return 100.0 * float(np.std(h) / np.mean(h))


def in_force(ks: np.ndarray, i: np.ndarray) -> np.ndarray:
    """Index into a trajectory (changes after samples ``ks``, ascending) of the calibration in
    force for samples ``i`` (−1: none yet)."""
    return np.searchsorted(ks, i, side="left") - 1


def spread_traj_pct(m, ks, offsets, matrices, start: int, lag: int = 0) -> float:
    """Spread of samples start… each calibrated with the calibration in force ``lag`` samples
    before it (lag 0: just before it)."""
    i = np.arange(start, len(m))
    j = in_force(ks, i - lag)
    h = np.empty((len(i), 3))
    for u in np.unique(j):
        sel = j == u
        if u < 0:
            h[sel] = m[i[sel]]
        else:
            h[sel] = (m[i[sel]] - offsets[u]) @ matrices[u].T
    nh = np.linalg.norm(h, axis=1)
    return 100.0 * float(np.std(nh) / np.mean(nh))


def snapshot_pct(m, ks, offsets, matrices, start: int) -> float:
    vals = []
    for s in range(start, len(m), SNAPSHOT_EVERY):
        u = int(in_force(ks, np.array([s]))[0])
        if u >= 0:
            vals.append(spread_pct(m[start:], offsets[u], matrices[u]))
    return float(np.mean(vals)) if vals else float("nan")


def lag_of(n: int) -> int:
    return min(500, n // 3)


def online_figures(m, traj, splits=SPLITS) -> dict[str, dict[str, float]]:
    """{split: {causal, lagged, snapshot}} for one trajectory [(k, V, W)]."""
    ks = np.array([k for k, _, _ in traj])
    V = np.array([v for _, v, _ in traj])
    W = np.array([w for _, _, w in traj])
    out = {}
    for f in splits:
        k = int(len(m) * f)
        out[f"{f:.1f}"] = {
            "causal": spread_traj_pct(m, ks, V, W, k),
            "lagged": spread_traj_pct(m, ks, V, W, k, lag_of(len(m))),
            "snapshot": snapshot_pct(m, ks, V, W, k),
        }
    return out


def static_cells(n: int, splits=SPLITS) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, train indices, test indices) for the 10 cells of one recording."""
    cells = []
    for f in splits:
        k = int(n * f)
        cells.append((f"split {f:.0%}", np.arange(k), np.arange(k, n)))
    edges = np.linspace(0, n, FOLDS + 1).astype(int)
    for j in range(FOLDS):
        test = np.arange(edges[j], edges[j + 1])
        cells.append((f"fold {j + 1}", np.r_[0:edges[j], edges[j + 1]:n], test))
    return cells


# -- the peer ------------------------------------------------------------------------------
def mc_static(figs, name, t, m, label, train, test, seeds) -> float:
    """Median over seeds of MotionCal's held-out spread for one cell."""
    tt = joined_times(t, train)
    d = peer.digest(tt, m[train])
    vals = [figs.get(f"static|{name}|{label}|{s}|{d}",
                     lambda s=s: spread_pct(m[test], *peer.final(tt, m[train], s))) for s in seeds]
    return float(np.median(vals))


def mc_online(figs, name, t, m, seeds, splits=SPLITS) -> dict[str, dict[str, float]]:
    """{split: {causal, lagged, snapshot}}: medians over seeds of MotionCal online."""
    d = peer.digest(t, m)
    tag = "" if tuple(splits) == SPLITS else "|" + ",".join(f"{f:.2f}" for f in splits)
    per_seed = [figs.get(f"online|{name}|{s}|{d}{tag}", lambda s=s: online_figures(m, peer.trace(t, m, s), splits))
                for s in seeds]
    return {sp: {k: float(np.median([ps[sp][k] for ps in per_seed])) for k in per_seed[0][sp]}
            for sp in per_seed[0]}


def magcal_static(m, train, test) -> float:
    r = fit_calibration(m[train], model="auto")
    return spread_pct(m[test], r.calibration.offset_ut, r.calibration.soft_iron) if r else float("nan")


def gmean(x) -> float:
    return float(np.exp(np.mean(np.log(np.asarray(x, dtype=float)))))


# -- magcal's side -------------------------------------------------------------------------
def tracker_trajectory(t, m) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """[(k, V, W)] of the calibrations ``Tracker`` put in force (a withdrawal = none: raw)."""
    out = []
    for ev in Tracker().add_many(m, t):
        if isinstance(ev, Estimate):
            out.append((ev.sample, ev.calibration.offset_ut, ev.calibration.soft_iron))
        else:
            out.append((ev.sample, np.zeros(3), np.eye(3)))
    return out


def floor_pct(m, k) -> float:
    """The in-sample ellipsoid floor: the plain ML ellipsoid of the judged part itself. Unweighted:
    `fit`'s direction and visit weights give up in-sample fit for what lies off the sample, so a
    weighted fit is no floor."""
    r = fit_calibration(m[k:], model="ellipsoid", balance="none")
    return spread_pct(m[k:], r.calibration.offset_ut, r.calibration.soft_iron) if r else float("nan")


# -- tables --------------------------------------------------------------------------------
def static_table(recs, figs, seeds, splits) -> dict:
    print(f"\n## Static: magcal fit / MotionCal over {len(splits)} split points and {FOLDS} folds "
          f"(MotionCal: median of {len(seeds)} seeds per cell)\n")
    print("| recording | cells | gmean ratio | cells no worse | worst cell | best cell |")
    print("|---|---|---|---|---|---|")
    allr, per = [], {}
    for name, (t, m) in recs.items():
        r = np.array([magcal_static(m, tr, te) / mc_static(figs, name, t, m, label, tr, te, seeds)
                      for label, tr, te in static_cells(len(m), splits)])
        figs.save()
        refused = int(np.sum(~np.isfinite(r)))
        r = r[np.isfinite(r)]
        per[name] = gmean(r)
        allr += list(r)
        note = f" ({refused} refused: coverage)" if refused else ""
        print(f"| {name} | {len(r)}{note} | {per[name]:.3f} | {int(np.sum(r <= 1))} | {r.max():.3f} | {r.min():.3f} |",
              flush=True)
    g = gmean(allr)
    print(f"\nstatic geometric mean over {len(allr)} cells: {g:.3f} (target ≤ 0.95); no worse in "
          f"{int(np.sum(np.array(allr) <= 1))}; worst recording {max(per.values()):.3f} (target ≤ 1.02)")
    return {"gmean": g, "per_recording": per}


def _online_row(name, t, m, figs, seeds, splits):
    mc = mc_online(figs, name, t, m, seeds, splits)
    figs.save()
    c0 = time.process_time()
    traj = tracker_trajectory(t, m)
    cpu = time.process_time() - c0
    ours = online_figures(m, traj, splits)
    keys = ("causal", "lagged", "snapshot")
    row = {k: gmean([ours[s][k] / mc[s][k] for s in ours]) for k in keys}
    fl = [x for x in (ours[s]["causal"] / floor_pct(m, int(len(m) * float(s))) for s in ours) if np.isfinite(x)]
    row.update(floor=gmean(fl) if fl else float("nan"), floor_min=min(fl, default=float("nan")), us=1e6 * cpu / len(m))
    row["abs"] = {k: (gmean([ours[s][k] for s in ours]), gmean([mc[s][k] for s in ours])) for k in keys}
    return row


def online_table(recs, figs, seeds, splits) -> dict:
    print(f"\n## Online: magcal tracker / MotionCal online, judged after each of {len(splits)} split points "
          f"(MotionCal: median of {len(seeds)} seeds)\n")
    print("| recording | causal % magcal / MotionCal | ratio | lagged ratio | snapshot ratio | "
          "causal / in-sample floor (min over splits) | tracker CPU µs/sample |")
    print("|---|---|---|---|---|---|---|")
    rows = {}
    for name, (t, m) in recs.items():
        r = rows[name] = _online_row(name, t, m, figs, seeds, splits)
        a, b = r["abs"]["causal"]
        print(f"| {name} | {a:.3f} / {b:.3f} | {r['causal']:.3f} | {r['lagged']:.3f} | {r['snapshot']:.3f} | "
              f"{r['floor']:.3f} ({r['floor_min']:.3f}) | {r['us']:.0f} |", flush=True)
    g = {k: gmean([r[k] for r in rows.values()]) for k in ("causal", "lagged", "snapshot")}
    floors = [r["floor"] for r in rows.values() if np.isfinite(r["floor"])]
    print(f"\ngeometric mean: causal {g['causal']:.3f} (target ≤ 0.94), lagged {g['lagged']:.3f} (≤ 0.98), "
          f"snapshot {g['snapshot']:.3f} (≤ 0.98); worst causal {max(r['causal'] for r in rows.values()):.3f} "
          f"(≤ 1.05); lowest causal/floor {min(floors, default=float('nan')):.3f} (≥ 0.99)")
    return {"gmean": g, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--static", action="store_true", help="only the static table")
    ap.add_argument("--online", action="store_true", help="only the online table")
    ap.add_argument("--seeds", type=int, default=SEEDS, help="MotionCal seeds per cell (median)")
    ap.add_argument("--seed0", type=int, default=1, help="first MotionCal seed (fresh seeds: e.g. 101)")
    ap.add_argument("--splits", default=",".join(str(f) for f in SPLITS),
                    help="split points (fractions), e.g. 0.35,0.45,0.55,0.65 for held-out splits")
    ap.add_argument("--only", action="append", help="only this recording (repeatable)")
    ap.add_argument("--unseen", action="store_true",
                    help="the nine other raw recordings instead of the seven (umich, Betaflight, estibone)")
    a = ap.parse_args(argv)
    splits = tuple(float(x) for x in a.splits.split(","))
    seeds = range(a.seed0, a.seed0 + a.seeds)
    recs = {k: v for k, v in (unseen_recordings() if a.unseen else recordings()).items() if not a.only or k in a.only}
    figs = peer.Figures()
    try:
        if not a.online:
            static_table(recs, figs, seeds, splits)
        if not a.static:
            online_table(recs, figs, seeds, splits)
    except peer.NoDriver as exc:
        print(f"\n{exc}", file=sys.stderr)
        return 2
    finally:
        figs.save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
