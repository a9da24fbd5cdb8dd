"""magcal beside pymavlink's magfit_WMM.py on an ArduPilot log, judged the same way.

    python bench/flightlogs.py [LOG.bin] [--blocks 5] [--out bench/results/flightlogs.md]

LOG defaults to ``$MAGCAL_REAL_DATA/ardupilot_solo_log171/log171.bin``. For every compass of the
log, the samples are cut into contiguous time blocks; each block is held out in turn, both tools
fit the rest, and both are judged on the held-out block against the same expected field (the
log's attitude with AHRS_TRIM, and the World Magnetic Model at the log's GPS position and date):
the RMS of the vector residual |h − h_expected| and of the magnitude residual |h| − |h_expected|,
averaged over the blocks. magfit_WMM.py (installed with pymavlink) runs unmodified as a separate
process on a copy of the log, its training blocks chosen by its own ``--condition`` option:

* ``magfit --cmot`` as shipped: it reads the current from BAT messages only, so on a log that
  carries it in CURR (ArduCopter 3.3 and older) its current term stays at zero;
* ``magfit --cmot (CURR as BAT)``: the same script with CURR presented to it as BAT (amps);
* ``magfit --cmot --elliptical (CURR as BAT)``: with diagonals and off-diagonals too.

Its parameters are applied the way it defines them (its own raw field: the logged field with the
log's matrix undone, minus the logged integer offsets; corrected = M·(s·(raw + OFS)) + MOT·I).
The current coefficients are compared on the whole log: magcal's (with its motors-running step,
and without it as magfit fits), and magfit's MOT expressed the same way (k = −M⁻¹·MOT, µT/A).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

SHIM = r"""
import atexit, os, runpy, sys
atexit.register(lambda: sys.stderr.write("\ncpu_s %.3f\n" % sum(os.times()[:2])))
script, patch = sys.argv[1], sys.argv[2] == "curr-as-bat"
sys.argv = sys.argv[1:2] + sys.argv[3:]
from pymavlink import mavutil
_orig = mavutil.mavlink_connection
class _Bat:
    def __init__(self, m):
        self._m = m
        self.Curr = m.Curr / 100.0 if isinstance(m.Curr, int) else m.Curr
    def get_type(self):
        return "BAT"
    def __getattr__(self, k):
        return getattr(self._m, k)
class _Conn:
    def __init__(self, c):
        self._c = c
    def recv_match(self, type=None, **kw):
        want = isinstance(type, (list, tuple)) and "BAT" in type
        if want:
            type = [t for t in type if t != "BAT"] + ["CURR"]
        m = self._c.recv_match(type=type, **kw)
        return _Bat(m) if want and m is not None and m.get_type() == "CURR" else m
    def __getattr__(self, k):
        return getattr(self._c, k)
if patch:
    mavutil.mavlink_connection = lambda *a, **k: _Conn(_orig(*a, **k))
runpy.run_path(script, run_name="__main__")
"""

VARIANTS = (
    ("magfit --cmot", ["--cmot"], False),
    ("magfit --cmot (CURR as BAT)", ["--cmot"], True),
    ("magfit --cmot --elliptical (CURR as BAT)", ["--cmot", "--elliptical"], True),
)


def magfit_script() -> str:
    path = shutil.which("magfit_WMM.py") or os.path.join(os.path.dirname(sys.executable), "magfit_WMM.py")
    if not os.path.exists(path):
        sys.exit("magfit_WMM.py not found: it is installed with pymavlink (pip install '.[logs]')")
    return path


CACHE: dict = {"dir": None}


def run_magfit(log: str, mag_no: int, flags: list[str], shim: bool, condition: str | None) -> dict:
    """``run_magfit_now``, its result kept in ``--cache DIR`` (keyed by the log's bytes and the
    arguments) so that an interrupted bench does not run magfit again."""
    if CACHE["dir"] is None:
        return run_magfit_now(log, mag_no, flags, shim, condition)
    with open(log, "rb") as fh:
        digest = hashlib.sha1(fh.read()).hexdigest()
    key = hashlib.sha1(json.dumps([digest, mag_no, flags, shim, condition]).encode()).hexdigest()
    path = os.path.join(CACHE["dir"], key + ".json")
    if os.path.exists(path):
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    out = run_magfit_now(log, mag_no, flags, shim, condition)
    with open(path + ".tmp", "w", encoding="utf-8") as fh:
        json.dump(out, fh)
    os.replace(path + ".tmp", path)
    return out


def run_magfit_now(log: str, mag_no: int, flags: list[str], shim: bool, condition: str | None) -> dict:
    """Its printed parameters (name → value), the earth-field strength it used, its CPU seconds.
    The script runs unmodified (``runpy``); the shim only reports its CPU time and, with
    ``shim``, presents CURR as BAT to it."""
    args = ["--mag", str(mag_no), "--att-source", "ATT", *flags]
    if condition:
        args += ["--condition", condition]
    argv = [sys.executable, "-c", SHIM, magfit_script(), "curr-as-bat" if shim else "as-shipped", *args, log]
    env = dict(os.environ, MPLBACKEND="Agg", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=os.path.dirname(log))
    cpu = re.search(r"^cpu_s ([\d.]+)$", out.stderr, re.M)
    params = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(COMPASS_\w+) (-?[\d.]+)$", out.stdout, re.M)}
    strength = re.search(r"strength (\d+)", out.stdout)
    if not params:  # its own optimiser gave up ("Fit failed: Iteration limit reached" …)
        why = re.search(r"Fit failed: (.*)", out.stdout)
        return {"params": None, "failure": why.group(1).strip() if why else (out.stderr.strip()[-200:] or "no output"),
                "strength_mg": None, "cpu_s": float(cpu.group(1)) if cpu else 0.0}
    return {"params": params, "strength_mg": float(strength.group(1)) if strength else None,
            "cpu_s": float(cpu.group(1)) if cpu else 0.0}


def magfit_correct(p: dict, index: int, raw_mg: np.ndarray, current_a: np.ndarray) -> np.ndarray:
    """magfit_WMM's own correction of its raw field with its printed parameters (mG): ArduPilot's
    formula with COMPASS_* names, MOT per amp."""
    from magcal.recordings.logs import conventions as cv

    return cv.ap_correct(raw_mg, cv.ap_compass({**p, "COMPASS_MOTCT": 2}, index), current_a)


def magfit_raw(log_path: str, lm, index: int) -> np.ndarray:
    """magfit's raw field: the logged one with the log's matrix and motor offset undone, minus
    the integer offsets logged in the MAG message (it uses those, not the parameters)."""
    from pymavlink import DFReader

    from magcal.recordings.logs import conventions as cv

    name = lm.info.name
    r = DFReader.DFReader_binary(log_path, zero_time_base=False)
    ofs = []
    while (m := r.recv_match(type=name)) is not None:
        ofs.append((m.OfsX, m.OfsY, m.OfsZ))
    comp = cv.ap_compass(lm.log.params, index)
    logged = lm.log.mag_fields[[i.index for i in lm.log.mags].index(index)].values
    return np.linalg.solve(comp.matrix, logged.T).T / comp.scale - np.asarray(ofs, float)


def rms_pair(h: np.ndarray, expected: np.ndarray) -> tuple[float, float]:
    vec = float(np.sqrt(np.mean(np.sum((h - expected) ** 2, axis=1))))
    mag = float(np.sqrt(np.mean((np.linalg.norm(h, axis=1) - np.linalg.norm(expected, axis=1)) ** 2)))
    return vec, mag


def magcal_fold(lm, train, test, step=True) -> tuple[float, float, np.ndarray]:
    """Held-out (vector RMS, |m| RMS) of magcal's fit to the training blocks (its own term
    choice), and the current coefficient of that fit (fitted whether kept or not)."""
    from magcal.fit.vector import fit_vector, motors_on

    s = lm.series
    ch = {k: v[train] for k, v in s.channels.items()}
    r = fit_vector(s.field_ut[train], ch, lm.earth_body_ut[train], lm.earth_field_ut, term="current_a", step=step)
    test_ch = {k: v[test] for k, v in s.channels.items()}
    on = motors_on(s.channels, min_fraction=0.0)
    if on is not None:
        test_ch["motors_on"] = on[test]
    k = next(np.array(t["coef_ut_per_unit"]) for t in r.terms if t["channel"] == "current_a")
    return (*rms_pair(r.calibration.correct(s.field_ut[test], test_ch), lm.earth_body_ut[test]), k)


def folds(n: int, blocks: int):
    edges = np.linspace(0, n, blocks + 1).round().astype(int)
    for lo, hi in zip(edges[:-1], edges[1:]):
        test = np.zeros(n, bool)
        test[lo:hi] = True
        yield ~test, test


def condition_outside(name: str, field: str, t0_s: float, t1_s: float) -> str:
    """magfit's --condition keeping the messages outside [t0, t1] of this compass's clock."""
    scale = 1e6 if field == "TimeUS" else 1e3
    return f"{name}.{field} < {t0_s * scale:.0f} or {name}.{field} > {t1_s * scale:.0f}"


def time_field(log_path: str, name: str) -> str:
    from pymavlink import DFReader

    m = DFReader.DFReader_binary(log_path, zero_time_base=False).recv_match(type=name)
    return "TimeUS" if "TimeUS" in m._fieldnames else "TimeMS"


def magfit_k(p: dict, index: int) -> np.ndarray:
    """magfit's COMPASS_MOT as magcal's current coefficient: k = −(s·M)⁻¹·MOT, µT/A."""
    suffix = "" if index == 0 else str(index + 1)
    d, o = [p.get(f"COMPASS_DIA{suffix}_{a}", 1.0) for a in "XYZ"], [p.get(f"COMPASS_ODI{suffix}_{a}", 0.0) for a in "XYZ"]
    m = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    mot = np.array([p.get(f"COMPASS_MOT{suffix}_{a}", 0.0) for a in "XYZ"])
    return -np.linalg.solve(m, mot) / p.get(f"COMPASS_SCALE{suffix}", 1.0) * 0.1


def jackknife_sigma(ks: list) -> np.ndarray | None:
    """Delete-one-block jackknife σ of a coefficient from its fits with each block left out."""
    k = np.array([x for x in ks if np.all(np.isfinite(x))])
    if len(k) < 3:
        return None
    return np.sqrt((len(k) - 1) / len(k) * np.sum((k - k.mean(axis=0)) ** 2, axis=0))


def magcal_whole(lm) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, k µT/A, stated σ) of magcal's current term on the whole log, with and without its step."""
    from magcal.fit.vector import fit_vector

    s, out = lm.series, []
    for label, step in (("magcal", True), ("magcal (no step)", False)):
        r = fit_vector(s.field_ut, s.channels, lm.earth_body_ut, lm.earth_field_ut, term="current_a", step=step)
        t = next(x for x in r.terms if x["channel"] == "current_a")
        kept = "" if t["kept"] else " (not kept)"
        out.append((label + kept, np.array(t["coef_ut_per_unit"]), np.array(t["sigma_ut_per_unit"])))
    return out


def start_compass(pool, log_path: str, lm, index: int, blocks: int, variants) -> dict:
    """Submit every magfit run of one compass (each held-out block and the whole log, per
    variant) to ``pool``; magcal's fits run meanwhile."""
    s = lm.series
    field = time_field(log_path, lm.info.name)
    runs, magcal = {}, {"magcal": [], "magcal (no step)": []}
    for i, (train, test) in enumerate(folds(len(s), blocks)):
        cond = condition_outside(lm.info.name, field, s.t_s[test][0] - 0.001, s.t_s[test][-1] + 0.001)
        for label, flags, shim in variants:
            runs[label, i] = pool.submit(run_magfit, log_path, index + 1, flags, shim, cond)
    for label, flags, shim in variants:
        runs[label, None] = pool.submit(run_magfit, log_path, index + 1, flags, shim, None)
    for train, test in folds(len(s), blocks):
        magcal["magcal"].append(magcal_fold(lm, train, test))
        magcal["magcal (no step)"].append(magcal_fold(lm, train, test, step=False))
    return {"lm": lm, "index": index, "blocks": blocks, "variants": variants, "runs": runs, "magcal": magcal,
            "whole": magcal_whole(lm), "raw_mf": magfit_raw(log_path, lm, index)}


def finish_compass(job: dict) -> dict:
    """The held-out rows and the coefficient rows once the magfit runs are done."""
    lm, index, s = job["lm"], job["index"], job["lm"].series
    cur = s.channels.get("current_a", np.zeros(len(s)))
    rows = {k: [v[:2] for v in vals] for k, vals in job["magcal"].items()}
    fold_k = {k: [v[2] for v in vals] for k, vals in job["magcal"].items()}
    cpu, strength = {}, None
    for label, _, _ in job["variants"]:
        rows[label], fold_k[label], cpu[label] = [], [], 0.0
        for i, (_, test) in enumerate(folds(len(s), job["blocks"])):
            mf = job["runs"][label, i].result()
            cpu[label] += mf["cpu_s"]
            if mf["params"] is None:
                rows[label].append((np.nan, np.nan))
                fold_k[label].append(np.full(3, np.nan))
                continue
            strength = mf["strength_mg"] or strength
            h = magfit_correct(mf["params"], index, job["raw_mf"][test], cur[test]) * 0.1
            rows[label].append(rms_pair(h, lm.earth_body_ut[test]))
            fold_k[label].append(magfit_k(mf["params"], index))
    coefs = [(label, k, sig, jackknife_sigma(fold_k[label.split(" (not kept)")[0]])) for label, k, sig in job["whole"]]
    for label, _, _ in job["variants"]:
        mf = job["runs"][label, None].result()
        cpu[label] += mf["cpu_s"]
        if mf["params"] is None:
            coefs.append((f"{label}: failed ({mf['failure']})", np.full(3, np.nan), None, None))
        else:
            coefs.append((label, magfit_k(mf["params"], index), None, jackknife_sigma(fold_k[label])))
    return {"rows": rows, "cpu": cpu, "coefficients": coefs, "magfit_strength_mg": strength}


def format_compass(lm, res: dict) -> list[str]:
    info = lm.info
    where = "external" if info.external else "internal"
    lines = [f"### {info.name} ({where}, {info.device})", "",
             "| fit | held-out vector RMS µT (mean of blocks) | per block | held-out |m| RMS µT |",
             "|---|---|---|---|"]
    for label, vals in res["rows"].items():
        v = np.array(vals)
        failed = int(np.isnan(v[:, 0]).sum())
        note = f" ({failed} of {len(v)} blocks: its optimiser gave up, mean of the rest)" if failed else ""
        lines.append(f"| {label}{note} | {np.nanmean(v[:, 0]):.2f} | {' '.join(f'{x:.1f}' for x in v[:, 0])} "
                     f"| {np.nanmean(v[:, 1]):.2f} |")
    lines += ["", "| current coefficient, whole log | k µT/A (x, y, z) | stated σ | jackknife σ (held-out blocks) | CPU s (magfit runs) |",
              "|---|---|---|---|---|"]
    fmt = lambda v: "—" if v is None else "(" + ", ".join(f"{x:.3f}" for x in v) + ")"  # noqa: E731
    for label, k, sig, jack in res["coefficients"]:
        cpu = res["cpu"].get(label.split(":")[0])
        lines.append(f"| {label} | ({', '.join(f'{x:+.3f}' for x in k)}) | {fmt(sig)} | {fmt(jack)} | "
                     + ("—" if cpu is None else f"{cpu:.0f}") + " |")
    strength = res["magfit_strength_mg"]
    lines += ["", f"Expected field: {lm.earth_model} {lm.earth_field_ut:.2f} µT (magcal); magfit's own table "
              f"{strength / 10:.2f} µT." if strength else "", ""]
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = os.path.join(os.environ.get("MAGCAL_REAL_DATA", ""), "ardupilot_solo_log171", "log171.bin")
    ap.add_argument("log", nargs="?", default=default, help="an ArduPilot DataFlash .bin log")
    ap.add_argument("--blocks", type=int, default=5, help="held-out time blocks (default 5)")
    ap.add_argument("--mags", default=None, help="compasses to compare, e.g. 0,2 (default all)")
    ap.add_argument("--out", default=None, help="also write the table to this markdown file")
    ap.add_argument("--variants", default=None,
                    help="magfit variants to run, by number from 0 (" + "; ".join(f"{i}: {v[0]}" for i, v in enumerate(VARIANTS))
                    + "; default all)")
    ap.add_argument("--cache", default=None, help="keep each magfit result in this directory (a re-run reuses them)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                    help="magfit runs at once (each a separate process; default: the CPU count)")
    args = ap.parse_args(argv)
    if not os.path.exists(args.log):
        ap.error(f"no log at {args.log!r}: give LOG or set MAGCAL_REAL_DATA")
    from magcal.recordings.logs import read_log, select

    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        log_path = shutil.copy(args.log, tmp)  # magfit writes beside the log it reads
        log = read_log(log_path)
        wanted = [m.index for m in log.mags] if args.mags is None else [int(x) for x in args.mags.split(",")]
        lines = [f"## magcal vs magfit_WMM.py on {os.path.basename(args.log)} ({log.firmware}), "
                 f"{args.blocks} held-out time blocks", ""]
        variants = VARIANTS if args.variants is None else tuple(VARIANTS[int(i)] for i in args.variants.split(","))
        if args.cache:
            os.makedirs(args.cache, exist_ok=True)
            CACHE["dir"] = args.cache
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            jobs = [start_compass(pool, log_path, select(log, i), i, args.blocks, variants) for i in wanted]
            magcal_cpu = time.process_time() - t0
            for job in jobs:
                part = format_compass(job["lm"], finish_compass(job))
                lines += part
                print("\n".join(part), flush=True)
    lines.append(f"magcal's own CPU (reading, all its fits): {magcal_cpu:.1f} s")
    print(lines[-1])
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
