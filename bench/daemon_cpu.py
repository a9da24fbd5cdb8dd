"""CPU share of the host while streaming at 100 Hz: device → ProtocolDevice → SphereAccumulator
(what a calibration daemon does per sample, without the session's gates).

Run: python bench/daemon_cpu.py [seconds]   (default 20 per measurement)

Two figures, each CPU time (``time.process_time``) over wall time of the measuring process:

1. **host only** — measured twice: waking for every line, and a batch loop that sleeps 50 ms
   between reads (what a daemon needs: nothing is lost, the port buffers). The simulated board (``SimBoard``, real-time pace) runs in a child process
   behind a pseudo-terminal and the host opens the pty as a serial port, exactly as it opens
   ``/dev/ttyACM0``; only the host's CPU is counted. Target (issue 2): < 2 % of one core.
2. **host + in-process board** — ``sim://?pace=1&rate=100`` in the same process, so the
   simulator's physics (and its 5 ms polling) is included: an upper bound, not the host's cost.
"""

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.core.sample import Sample  # noqa: E402
from magcal.devices import open_device  # noqa: E402
from magcal.fit import SphereAccumulator  # noqa: E402


def stream(dev, seconds: float, poll_s: float = 0.0) -> tuple[int, float, float]:
    """Stream for ``seconds``. ``poll_s`` = 0: wake for every arriving line (lowest latency);
    > 0: sleep that long between reads and take what has arrived (a daemon's batch loop)."""
    dev.open()
    dev.start(100)
    acc = SphereAccumulator()
    n = 0
    wall0, cpu0 = time.monotonic(), time.process_time()
    while time.monotonic() - wall0 < seconds:
        if poll_s:
            time.sleep(poll_s)
        items = dev.read(0.001 if poll_s else 0.1)
        batch = [s.field_ut for s in items if isinstance(s, Sample) and s.valid]
        if batch:
            acc.add_batch(np.array(batch))
            n += len(batch)
    wall, cpu = time.monotonic() - wall0, time.process_time() - cpu0
    dev.stop()
    dev.close()
    return n, wall, cpu


def board_process(master_fd: int) -> None:
    """Child: the simulated board, real time, speaking over the pty master."""
    from magcal.devices.simboard import SimBoard, serve_fd

    board = SimBoard(rate_hz=100, pace=1.0)
    board.timeout = 0.02
    serve_fd(board, master_fd)


def report(label: str, n: int, wall: float, cpu: float) -> None:
    print(f"{label}: {n} samples in {wall:.1f} s ({n / wall:.1f} Hz); "
          f"CPU {cpu:.3f} s = {100 * cpu / wall:.2f} % of one core")


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 20.0
    import tty

    for poll_s, label in ((0.0, "every line"), (0.05, "batch loop, 50 ms")):
        master, slave = os.openpty()
        tty.setraw(slave)
        path = os.ttyname(slave)
        pid = os.fork()
        if pid == 0:  # child
            os.close(slave)
            try:
                board_process(master)
            finally:
                os._exit(0)
        os.close(master)
        try:
            n, wall, cpu = stream(open_device(path), seconds, poll_s)
            report(f"host only, {label} (board in a child process, over a pty)", n, wall, cpu)
        finally:
            os.kill(pid, 15)
            os.waitpid(pid, 0)
            os.close(slave)
    print("  target < 2 % of one core")
    n, wall, cpu = stream(open_device("sim://?pace=1&rate=100"), seconds)
    report("host + in-process sim:// board (upper bound)", n, wall, cpu)


if __name__ == "__main__":
    main()
