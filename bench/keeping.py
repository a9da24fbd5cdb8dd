"""Keeping a calibration for a day: the tracker's cost, and the daemon's EEPROM writes.

The sensor: the physics simulator's board (``demo_scenario``: hard iron, a little soft iron,
0.4 µT noise) with an offset that wanders as the sensor twin models it (``sim.wander``: a sum of
Ornstein–Uhlenbeck components; here 0.5 µT with a 4 h correlation time — a day's temperature —
and 0.15 µT with 10 min), moved by hand-waving with a 60 s period, 100 Hz, for a simulated day.

``--cost``: the tracker alone (``fit.tracker.Tracker``) on that stream, hour by hour: process CPU
time per sample (amortised over each hour, refits included), samples in memory, the size of its
saved state, and the process's resident memory — all should stay flat — and how far its offset
is from the true one (the board's offset plus the wander at the hour's end), beside how far the
offset in force at the end of hour 1 would be had it been kept.

``--daemon``: the whole ``magcal run`` (``daemon.keep: tracker``, recalibration on) against the
simulated board, fast-forwarded (``pace=0``: the board produces samples as fast as the daemon
reads, and the daemon's wall clock is the board's simulated one, so the EEPROM budget refills at
the simulated day's pace): the writes the keeper made, each verified by read-back, the EEPROM
writes the board itself counted, hour by hour, and the budget (24 a day, 3 back to back by
default). The whole daemon costs about 0.3 ms of CPU per sample, so its day runs at
``--daemon-rate`` (10 Hz by default: the same wander, a tenth of the samples).

Run: python bench/keeping.py [--cost] [--daemon] [--hours H] [--daemon-rate HZ] [--seed N]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.app import config  # noqa: E402
from magcal.app.daemon import Collaborators, Daemon  # noqa: E402
from magcal.core.sample import UT_PER_COUNT, asa_gain  # noqa: E402
from magcal.devices.simboard import SimEeprom  # noqa: E402
from magcal.fit.tracker import Tracker  # noqa: E402
from magcal.sim.physics import Motion, demo_scenario  # noqa: E402
from magcal.sim import wander  # noqa: E402
from magcal.sim.wander import WanderComponent  # noqa: E402

RATE_HZ = 100
HOUR = 3600


def twin(seed: int):
    sc = demo_scenario(seed).with_physics(wander=(WanderComponent((0.5,) * 3, 4 * HOUR), WanderComponent((0.15,) * 3, 600.0)))
    return replace(sc, motion=Motion("sphere", period_s=60.0))


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def hour_of_samples(sc, hour: int) -> tuple[np.ndarray, np.ndarray]:
    """One simulated hour at RATE_HZ: (t (n,), m (n, 3) µT as the chip reports them)."""
    k = np.arange(hour * HOUR * RATE_HZ, (hour + 1) * HOUR * RATE_HZ)
    t = k / RATE_HZ
    m, _ = sc.field_ut(t, k)
    raw, _ = sc.to_counts(m)
    return t, raw * UT_PER_COUNT * np.array([asa_gain(a) for a in sc.physics.asa])


def cost(hours: float, seed: int) -> None:
    sc = twin(seed)
    trk = Tracker()
    offset0, w_first = np.asarray(sc.physics.truth().offset_ut), None
    print("| hour | tracker CPU µs/sample | samples in memory | saved state kB | RSS MiB | "
          "|offset − true offset| µT | same, calibration of hour 1 kept |")
    print("|---|---|---|---|---|---|---|")
    total_cpu, total_n = 0.0, 0
    for h in range(int(np.ceil(hours))):
        t, m = hour_of_samples(sc, h)
        c0 = cpu_s()
        trk.add_many(m, t)
        dc = cpu_s() - c0
        total_cpu, total_n = total_cpu + dc, total_n + len(t)
        w_now = wander.draw(sc.sensor.wander, sc.seed, t[-1:])[0][0]  # (offset (n, 3), field (n,)): the offset now
        w_first = w_first if h else w_now
        err = f"{np.linalg.norm(trk.estimate.calibration.offset_ut - (offset0 + w_now)):.3f}"
        stale = f"{np.linalg.norm(w_now - w_first):.3f}"
        state_kb = len(json.dumps(trk.to_state())) / 1024
        print(f"| {h + 1} | {1e6 * dc / len(t):.1f} | {int(trk.memory.valid.sum())} | {state_kb:.0f} | "
              f"{rss_mib():.0f} | {err} | {stale} |", flush=True)
    print(f"\ntracker: {1e6 * total_cpu / total_n:.1f} µs per sample amortised over {total_n} samples "
          f"({total_n / RATE_HZ / HOUR:.1f} h at {RATE_HZ} Hz); target ≤ 50")


def daemon(hours: float, seed: int, rate_hz: int) -> None:
    clock = {"t_s": 0.0}  # the board's simulated time of the last sample: the daemon's wall clock
    t0 = 1.8e9  # any epoch: only differences matter to the budget
    saves = []
    real = SimEeprom.put  # every EEPROM write of the board: a record, or the erase of one

    def counted(self, offset, payload):
        saves.append(clock["t_s"])
        return real(self, offset, payload)

    SimEeprom.put = counted
    n = int(hours * HOUR * rate_hz)
    with tempfile.TemporaryDirectory() as state_dir:
        settings = config.load(None, {"port": f"sim://?seed={seed}&pace=0&rate={rate_hz}", "rate_hz": rate_hz,
                                      "daemon": {"recalibrate": True, "keep": "tracker", "socket": False,
                                                 "state_every_s": 60.0}}, environ={})
        d = Daemon(settings, state_dir=state_dir, max_samples=n, collaborators=Collaborators(
                   device_options={"scenario": twin(seed)}, wall=lambda: t0 + clock["t_s"],
                   on_sample=lambda _e, s: clock.__setitem__("t_s", s.t_s)))
        c0 = cpu_s()
        d.run()
        cpu = cpu_s() - c0
    SimEeprom.put = real
    report_daemon(d, saves, hours, rate_hz, cpu)


def report_daemon(d, saves: list, hours: float, rate_hz: int, cpu: float) -> None:
    k = d.tracking.keeper
    b = k.budget
    per_hour = np.bincount((np.asarray(saves) // HOUR).astype(int), minlength=int(np.ceil(hours)))
    print(f"\ndaemon: {d.intake.samples} samples ({d.intake.samples / rate_hz / HOUR:.2f} h at {rate_hz} Hz, "
          f"simulated), {cpu:.0f} s CPU")
    print("EEPROM writes the board counted, hour by hour: " + " ".join(str(int(x)) for x in per_hour))
    print(f"keeper: {k.writes} writes verified by read-back, {k.failed} not verified; {k.cycles} EEPROM cycles "
          f"charged; the board counted {len(saves)} EEPROM writes")
    allowed = b.burst + b.per_day * hours / 24
    worst_day = max((sum(1 for s in saves if w <= s < w + 86400) for w in saves), default=0)
    print(f"budget: {b.per_day:g}/day, burst {b.burst}: at most {allowed:.1f} in {hours:g} h; "
          f"{'within' if len(saves) <= allowed and k.cycles == len(saves) else 'OVER'} the budget "
          f"(most in any 24 h window: {worst_day}); {b.years_to_rated_endurance:.1f} years to "
          f"the ATmega328P's rated 100 000 cycles at the full budget")
    waits = d.faults.get("write_budget_waits", 0)
    print(f"decisions that waited for the budget: {waits}; faults: {dict(d.faults)}")
    print(f"last decision: {json.dumps(d.tracking.last_decision)[:200]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cost", action="store_true")
    ap.add_argument("--daemon", action="store_true")
    ap.add_argument("--hours", type=float, default=24.0)
    ap.add_argument("--daemon-rate", type=int, default=10, help="the daemon's sample rate, Hz")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    both = not (a.cost or a.daemon)
    if a.cost or both:
        cost(a.hours, a.seed)
    if a.daemon or both:
        daemon(a.hours, a.seed, a.daemon_rate)


if __name__ == "__main__":
    main()
