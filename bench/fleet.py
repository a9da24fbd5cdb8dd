"""``magcal fleet`` at fleet size: are planted changes found at their flight, how often is an
unchanged vehicle called changed, how fast, and does a worker's memory stay flat?

    nice python bench/fleet.py [--vehicles 120] [--flights 12] [--speed-logs 120] [--seed 0] [--out FILE.md]

The logs are drawn by ``tests/fleet_twin.py`` from the real ArduPilot flight in tests/data (its
attitude, current and place; each vehicle's compasses are the simulator's sensor) and written as
ArduPilot DataFlash logs, so the analysis is the one a real log gets. A pilot vehicle is analysed
first for the per-flight σ of the hard iron (per axis, per compass) and of the current term;
then the vehicles are 40 % unchanged, 40 % with a hard-iron step on one compass of f × that σ
along a random direction (f cycling 2, 3, 5, 10), 20 % with a current term appearing on the
external compass (3, 5 or 10 × its σ); each change at a random flight between the first and the
last quarter. The fleet runs through ``app.fleet.job`` on a pool of 2 processes, as ``magcal
fleet`` runs it, with each worker's resident memory sampled every 100 logs. Then:

* found: the planted change named on the planted compass, of the planted kind, at the planted
  flight (and within one flight of it, and at all); per f;
* false: an unchanged vehicle with any change; and, on changed vehicles, any change other than
  the planted one;
* speed: ``--speed-logs`` of the logs analysed again into fresh results with 1 and then 2
  workers (wall and CPU), logs per hour per core from the CPU, and the speed-up — beside a
  control: the cores a busy loop gets as 1 and as 2 processes at that moment (on a shared
  machine the speed-up any work could have had);
* memory: each worker's RSS after every 100 logs (flat: the last sample within 10 % of the one
  after the first 100).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # as the magcal command sets them
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests"))

import fleet_twin as ft  # noqa: E402

STEP_FACTORS = (2, 3, 5, 10)
CURRENT_FACTORS = (3, 5, 10)


def _write(args):
    path, vehicle, j = args
    ft.write_flight(path, vehicle, j)
    return path


def write_all(root: str, vehicles, workers: int = 2) -> list[str]:
    jobs = []
    for v in vehicles:
        os.makedirs(os.path.join(root, v.name), exist_ok=True)
        jobs += [(os.path.join(root, v.name, f"flight_{j:03d}.bin"), v, j) for j in range(v.flights)]
    with ProcessPoolExecutor(workers) as pool:
        return list(pool.map(_write, jobs, chunksize=8))


def run(logs_root: str, results: str, workers: int, sample_rss: bool = False):
    """The fleet as ``magcal fleet`` runs it; (rows, wall s, CPU s of the workers, RSS samples)."""
    import psutil

    from magcal.app.fleet import job, store

    res = store.ResultStore(results)
    plan = job.plan([logs_root], res)
    me, samples, count = psutil.Process(), [], [0]

    def on_result(_):
        count[0] += 1
        if sample_rss and count[0] % 100 == 0:
            samples.append((count[0], sorted(c.memory_info().rss / 2 ** 20 for c in me.children())))

    cpu0 = os.times()
    t0 = time.monotonic()
    job.execute(plan, res, workers=workers, on_result=on_result)
    wall = time.monotonic() - t0
    cpu1 = os.times()
    cpu = (cpu1.children_user - cpu0.children_user + cpu1.children_system - cpu0.children_system
           + cpu1.user - cpu0.user + cpu1.system - cpu0.system)
    return res.rows(), wall, cpu, samples, len(plan.tasks)


def pilot_sigma(tmp: str) -> tuple[np.ndarray, np.ndarray]:
    """Median per-flight σ of the hard iron (compass × axis, µT) and of the current term (µT/A)."""
    v = ft.fleet(1, 6, seed=999)[0]
    ft.write_fleet(os.path.join(tmp, "pilot"), [v])
    rows, *_ = run(os.path.join(tmp, "pilot"), os.path.join(tmp, "pilot_results"), 2)
    sig = np.array([[r["sigma_offset_ut"] for r in rows if r["mag_index"] == c] for c in range(2)])
    cur = np.array([r["sigma_current_a_ut_per_unit"] for r in rows if r["mag_index"] == 0])
    return np.median(sig, axis=1), np.median(cur, axis=0)


def _direction(rng) -> np.ndarray:
    d = rng.normal(size=3)
    return d / np.linalg.norm(d)


def plan_fleet(n: int, flights: int, seed: int, sigma_off, sigma_cur):
    """The vehicles and, per vehicle, (kind, factor, compass, flight) of what was planted."""
    rng = np.random.default_rng(seed)
    plants, truth = [], []
    for i in range(n):
        share = i % 10
        at = int(rng.integers(flights // 4, flights - flights // 4 + 1))
        d = _direction(rng)
        if share < 4:
            plants.append(ft.Plant())
            truth.append(("none", 0, None, None))
        elif share < 8:
            f, c = STEP_FACTORS[i % len(STEP_FACTORS)], int(rng.integers(0, 2))
            s_along = float(np.sqrt(np.sum((d * sigma_off[c]) ** 2)))
            plants.append(ft.Plant("hard_iron_step", c, at, tuple(f * s_along * d)))
            truth.append(("hard_iron_step", f, c, at))
        else:
            f = CURRENT_FACTORS[i % len(CURRENT_FACTORS)]
            s_along = float(np.sqrt(np.sum((d * sigma_cur) ** 2)))
            plants.append(ft.Plant("current_appears", 0, at, tuple(f * s_along * d)))
            truth.append(("current_term_appeared", f, 0, at))
    return ft.fleet(n, flights, seed=seed, plants=plants), truth


def judge(rows, vehicles, truth) -> dict:
    from magcal.logic.fleet import detect

    report = detect(rows)
    board = {v.name: " ".join(v.board_line().split()) for v in vehicles}
    dev = {0: "device 97539", 1: "device 590114"}
    found, false_plain, extra, plain = {}, 0, 0, 0
    for v, (kind, f, c, at) in zip(vehicles, truth):
        ch = report.changes_of(board[v.name])
        if kind == "none":
            plain += 1
            false_plain += bool(ch)
            continue
        mine = [x for x in ch if x.kind.value == kind and x.compass == dev[c]]
        off = [abs(int(os.path.basename(x.flight)[7:10]) - at) for x in mine]
        found.setdefault((kind, f), []).append((0 in off, bool(off) and min(off) <= 1, bool(off)))
        extra += len(ch) - (1 if off else 0)
    return {"found": found, "false_plain": false_plain, "plain": plain, "extra": extra,
            "changed": len(vehicles) - plain}


def _report(j: dict, speed: dict, mem, sig_off, sig_cur, args) -> str:
    lines = [f"# fleet bench (seed {args.seed}, {args.vehicles} vehicles × {args.flights} flights)", "",
             f"per-flight σ (pilot, median): hard iron external {np.round(sig_off[0], 3)} µT, internal "
             f"{np.round(sig_off[1], 3)} µT; current term {np.round(sig_cur, 4)} µT/A", "",
             "| planted | × σ | vehicles | at the right flight | within one flight | found at all |",
             "|---|---|---|---|---|---|"]
    allc = []
    for (kind, f), hits in sorted(j["found"].items()):
        allc += hits
        cols = [f"{sum(h[k] for h in hits)} ({100 * np.mean([h[k] for h in hits]):.0f} %)" for k in range(3)]
        lines.append(f"| {kind} | {f} | {len(hits)} | " + " | ".join(cols) + " |")
    right = [h[0] for h in allc] or [False]
    lines += ["", f"all changed vehicles: {sum(right)}/{len(right)} found at the right flight "
              f"({100 * np.mean(right):.1f} %)",
              f"unchanged vehicles called changed: {j['false_plain']}/{j['plain']} "
              f"({100 * j['false_plain'] / max(j['plain'], 1):.1f} %)",
              f"other changes on changed vehicles: {j['extra']} on {j['changed']} vehicles", ""]
    for w, (wall, cpu, n) in sorted((k, v) for k, v in speed.items() if k != "control"):
        lines.append(f"{w} worker(s): {n} logs in {wall:.1f} s wall, {cpu:.1f} s CPU → "
                     f"{3600 * n / cpu:.0f} logs per hour per core, {3600 * n / wall:.0f} logs per hour")
    if 1 in speed and 2 in speed:
        lines.append(f"speed-up 1 → 2 workers (wall): {speed[1][0] / speed[2][0]:.2f}×")
    if "control" in speed:
        c = speed["control"]
        lines.append(f"control: a busy loop got {c[1]:.2f} cores as 1 process, {c[2]:.2f} as 2 — the speed-up this "
                     f"machine allowed then was {c[2] / c[1]:.2f}×")
    lines += ["", "worker RSS (MiB) every 100 logs: " + "; ".join(f"{n}: {rss}" for n, rss in mem)]
    if len(mem) >= 2:
        first, last = max(mem[0][1]), max(mem[-1][1])
        lines.append(f"largest worker after 100 logs {first:.0f} MiB, after {mem[-1][0]} logs {last:.0f} MiB "
                     f"({100 * (last - first) / first:+.1f} %)")
    lines.append(f"load average at the end: {os.getloadavg()}")
    return "\n".join(lines)


def _spin(seconds: float) -> int:
    t, n = time.monotonic(), 0
    while time.monotonic() - t < seconds:
        n += 1
    return n


def control_cores(seconds: float = 4.0) -> dict:
    """The processor this machine gives 1 and 2 busy processes right now (cores): the speed-up
    any work could have had, beside which the fleet's is read."""
    out = {}
    for w in (1, 2):
        c0, t0 = os.times(), time.monotonic()
        with ProcessPoolExecutor(w) as pool:
            list(pool.map(_spin, [seconds] * w))
        c1 = os.times()
        out[w] = (c1.children_user + c1.children_system - c0.children_user - c0.children_system) / (time.monotonic() - t0)
    return out


def speed_runs(logs_root: str, tmp: str, n: int) -> dict:
    """``n`` of the logs copied aside and analysed with 1 and then 2 workers into fresh results."""
    sub = os.path.join(tmp, "speed_logs")
    picked = sorted(os.path.join(d, f) for d, _, fs in os.walk(logs_root) for f in fs)[:n]
    for i, p in enumerate(picked):
        os.makedirs(os.path.join(sub, os.path.basename(os.path.dirname(p))), exist_ok=True)
        shutil.copy(p, os.path.join(sub, os.path.basename(os.path.dirname(p)), os.path.basename(p)))
    out = {"control": control_cores()}
    for w in (1, 2):
        _, wall, cpu, _, done = run(sub, os.path.join(tmp, f"speed_results_{w}"), w)
        out[w] = (wall, cpu, done)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--vehicles", type=int, default=120)
    ap.add_argument("--flights", type=int, default=12)
    ap.add_argument("--speed-logs", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed-only", action="store_true", help="only the speed runs, on --speed-logs unchanged logs")
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix="magcal-fleet-bench-")
    try:
        if args.speed_only:
            write_all(os.path.join(tmp, "logs"), ft.fleet(-(-args.speed_logs // args.flights), args.flights, args.seed))
            print(_report({"found": {}, "false_plain": 0, "plain": 0, "extra": 0, "changed": 0},
                          speed_runs(os.path.join(tmp, "logs"), tmp, args.speed_logs), [], np.zeros((2, 3)),
                          np.zeros(3), args))
            return
        sig_off, sig_cur = pilot_sigma(tmp)
        vehicles, truth = plan_fleet(args.vehicles, args.flights, args.seed, sig_off, sig_cur)
        t0 = time.monotonic()
        write_all(os.path.join(tmp, "logs"), vehicles)
        print(f"generated {args.vehicles * args.flights} logs in {time.monotonic() - t0:.0f} s", file=sys.stderr)
        rows, wall, cpu, mem, n = run(os.path.join(tmp, "logs"), os.path.join(tmp, "results"), 2, sample_rss=True)
        print(f"analysed {n} logs in {wall:.0f} s wall", file=sys.stderr)
        j = judge(rows, vehicles, truth)
        speed = speed_runs(os.path.join(tmp, "logs"), tmp, args.speed_logs) if args.speed_logs else {}
        text = _report(j, speed, mem, sig_off, sig_cur, args)
        print(text)
        if args.out:
            with open(args.out, "w", encoding="utf-8") as fh:
                fh.write(text + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
