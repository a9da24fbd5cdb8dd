"""Soak: one daemon streaming at 100 Hz for a simulated hour, fast-forwarded.

The ``sim://`` board runs unpaced (it produces samples as fast as the daemon reads them), so
an hour of 100 Hz data (360 000 samples) passes in a minute or two. Halfway through, a payload
adds hard iron; the daemon runs with recalibration on, the drift monitor, a rolling capture and
state written more often than at real time. Printed: process CPU time per simulated hour
(daemon and in-process simulator together: an upper bound of the daemon's share at real time),
RSS every 6 simulated minutes, and the daemon's decisions and fault counters. The simulator
caches noise blocks (``physics._block``, up to ~25 MiB); that cache is emptied at every mark
so that the RSS shown is the daemon's.

``--realtime S`` adds a paced run: S wall seconds at 100 Hz with the simulated board in a child
process behind a pseudo-terminal (the daemon opens it as a serial port, as it would open
/dev/ttyACM0), CPU time of the daemon's process over wall time — its share of one core when it
is not fast-forwarded, including the state writes every 5 s and the status socket.

Run: python bench/daemon_soak.py [--hours H] [--seed N] [--realtime S]
"""

import argparse
import os
import resource
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.app import config
from magcal.app.daemon import Collaborators, Daemon  # noqa: E402
from magcal.sim import physics  # noqa: E402

RATE_HZ = 100


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--realtime", type=float, default=0.0, metavar="S")
    args = ap.parse_args()
    if args.realtime:
        realtime(args.realtime, args.seed)
    n_total = int(args.hours * 3600 * RATE_HZ)
    half_s = args.hours * 1800
    with tempfile.TemporaryDirectory() as state_dir:
        port = f"sim://?pace=0&seed={args.seed}&fault=hard_iron@{half_s:g}=30.5,-38.2,14.8"
        settings = config.load(None, {"port": port, "rate_hz": RATE_HZ, "daemon": {
            "recalibrate": True, "capture_max_bytes": 8 << 20, "socket": False,
            # as often as at real time: every 5 s of data (the loop is fast-forwarded ~50×)
            "state_every_s": 0.1,
        }}, environ={})
        marks = []
        every = 36_000  # 6 simulated minutes
        t0, c0 = time.perf_counter(), cpu_s()

        def on_sample(epoch, s, state={"n": 0}):
            state["n"] += 1
            if state["n"] % every == 0:
                physics._block.cache_clear()
                marks.append((state["n"], time.perf_counter() - t0, cpu_s() - c0, rss_mib()))

        d = Daemon(settings, state_dir=state_dir, max_samples=n_total, collaborators=Collaborators(on_sample=on_sample))
        rss0 = rss_mib()
        d.run()
        wall, cpu = time.perf_counter() - t0, cpu_s() - c0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"simulated {d.intake.samples:,} samples = {d.intake.samples / RATE_HZ / 3600:.2f} h at {RATE_HZ} Hz "
              f"in {wall:.1f} s wall ({d.intake.samples / RATE_HZ / wall:.0f}× real time)")
        print(f"CPU {cpu:.1f} s per simulated {d.intake.samples / RATE_HZ / 3600:.2f} h  →  "
              f"{100 * cpu / (d.intake.samples / RATE_HZ):.2f} % of one core at real time")
        print(f"RSS at start {rss0:.1f} MiB, peak {peak:.1f} MiB; state saves {d.keeper.generation}")
        print(f"{'sim min':>8} {'wall s':>8} {'cpu s':>8} {'RSS MiB':>8}")
        for n, w, c, r in marks:
            print(f"{n / RATE_HZ / 60:8.0f} {w:8.1f} {c:8.1f} {r:8.1f}")
        if len(marks) >= 4:
            later = [r for *_, r in marks[len(marks) // 4:]]
            print(f"RSS drift over the last three quarters: {max(later) - min(later):+.2f} MiB")
        print("faults:", dict(d.faults))
        print("recalibrations:", d.writer.count, " capture:", d.capture.stats())
        for e in d.journal.entries:
            print(f"  at sample {e.get('at_sample', 0):>7}: {e['what']}")


def _serve_board(fd: int, seed: int) -> None:
    """Child process: a real-time simulated board on the pty master ``fd``."""
    from magcal.devices.simboard import SimBoard, serve_fd
    from magcal.sim.physics import demo_scenario

    board = SimBoard(demo_scenario(seed), rate_hz=RATE_HZ, pace=1.0)
    board.timeout = 0.01
    serve_fd(board, fd)


def realtime(seconds: float, seed: int) -> None:
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    pid = os.fork()
    if pid == 0:
        os.close(slave)
        try:
            _serve_board(master, seed)
        finally:
            os._exit(0)
    os.close(master)
    try:
        with tempfile.TemporaryDirectory() as state_dir:
            settings = config.load(None, {"port": os.ttyname(slave), "rate_hz": RATE_HZ,
                                          "daemon": {"recalibrate": True, "socket": True}}, environ={})
            d = Daemon(settings, state_dir=state_dir, max_samples=int(seconds * RATE_HZ))
            t0, c0 = time.perf_counter(), cpu_s()
            d.run()
            wall, cpu = time.perf_counter() - t0, cpu_s() - c0
    finally:
        os.kill(pid, 15)
        os.waitpid(pid, 0)
        os.close(slave)
    print(f"real time over a pty: {d.intake.samples} samples in {wall:.1f} s ({d.intake.samples / wall:.1f} Hz), "
          f"daemon CPU {cpu:.2f} s = {100 * cpu / wall:.2f} % of one core; state saves {d.keeper.generation}, "
          f"recalibrations {d.writer.count}, RSS {rss_mib():.1f} MiB")


if __name__ == "__main__":
    main()
