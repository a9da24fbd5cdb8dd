"""CPU time of ``diagnose()`` in-process and of the whole ``magcal diagnose FILE --json``.

    python3 bench/diagnose_speed.py [--runs N] [--no-command] [--only NAME]

On 5000-sample recordings: a simulated one (temperature channel, soft iron; the residual is white,
so no twin is drawn) and the first 5000 samples of three raw real recordings (whose residual
wanders, so every test is also run on the twin's draws). In-process: ``time.process_time`` around
``diagnose()`` after one warm-up, median of ``--runs``, one BLAS thread. Whole command: the
recording written as a CSV, ``magcal diagnose FILE --json`` run ``--runs`` times, user + system CPU
of the child from the operating system's accounting, median. CPU, not wall time: the machine is
shared. The command runs with its bytecode cached, as an installed package runs (pip compiles
it at install; the warm-up run writes it here): PYTHONDONTWRITEBYTECODE is taken out of the
child's environment, since with it every run compiles magcal's modules afresh (about 0.06 s CPU
more on this machine); so are the MAGCAL_* variables (the benches' data paths, which the
command would read as its own settings). Targets: issue 14, 0.15 s in-process and 0.4 s for the
whole command; issue 40 (with the locate step and fit's held-out model choice), 0.3 s in-process.
``--no-command`` measures ``diagnose()`` alone; ``--only`` the recordings whose name holds it.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

import numpy as np  # noqa: E402

from magcal.core.series import Series  # noqa: E402
from magcal.diagnose import diagnose  # noqa: E402

N = 5000
REAL = ("hmc5883l_full_sphere", "lsm9ds1_ckexplorer", "umich_preflight_icm20948")


def recordings() -> dict:
    """name → Series of 5000 samples."""
    import diagnose_bench
    import diagnose_raw

    s, _ = diagnose_bench.sim_case("soft+temp", 20261123)
    out = {"simulated soft+temp": s}
    for name, (t, m) in diagnose_raw.load_sources(set(REAL), N).items():
        out[name] = Series(t_s=t, field_ut=m)
    return out


def in_process(s: Series, runs: int) -> float:
    diagnose(s)
    cpu = []
    for _ in range(runs):
        c0 = time.process_time()
        diagnose(s)
        cpu.append(time.process_time() - c0)
    return float(np.median(cpu))


def command(s: Series, runs: int) -> float:
    cols = [s.t_s, *s.field_ut.T] + list(s.channels.values())
    header = ",".join(["t_s", "mx_ut", "my_ut", "mz_ut"] + list(s.channels))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "rec.csv")
        np.savetxt(path, np.column_stack(cols), delimiter=",", header=header, comments="", fmt="%.6f")
        cmd = [sys.executable, "-m", "magcal", "diagnose", path, "--json"]
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE" and not k.startswith("MAGCAL_")}
        subprocess.run(cmd, capture_output=True, check=True, env=env)  # warm-up (file cache, .pyc)
        cpu = []
        for _ in range(runs):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            subprocess.run(cmd, capture_output=True, check=True, env=env)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return float(np.median(cpu))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--no-command", action="store_true", help="measure diagnose() in-process only")
    ap.add_argument("--only", default="", help="only the recordings whose name holds this text")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    print(f"{'recording (5000 samples)':<28}{'diagnose() CPU s':>18}{'command CPU s':>15}")
    for name, s in recordings().items():
        if args.only not in name:
            continue
        whole = float("nan") if args.no_command else command(s, args.runs)
        print(f"{name:<28}{in_process(s, args.runs):>18.3f}{whole:>15.3f}", flush=True)
    print("targets: 0.300 in-process (issue 40; 0.150 issue 14), 0.400 the whole command (medians)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
