"""The EEPROM write budget under kill -9: 100 kills of ``magcal run`` at random moments, a third
right after the board stored a record, with a budget of 1 write a day (burst 1), over simulated
days.

Each boot is a forked daemon (``Daemon`` as ``magcal run`` builds it) against the simulated
board (``sim://?pace=0``) whose EEPROM was erased since the last boot, so the tracker wants to
write at once, every time. The daemon's wall clock is simulated: boot *i*
starts 2–30 h after boot *i − 1* and runs on the board's sample time from there, so the budget
refills at the simulated day's pace. The board's every EEPROM store is counted *before* it is
made (fsynced, with its simulated time): a count never below what the board took.

After each kill it reports the board's stores, the write ledger's EEPROM commands
(``writes.jsonl``) and the state file's (``keeping.cycles``); after the next start the state
must say what the ledger says. Acceptance: at most 1 board store in any 24 h of simulated time
(with burst 1: consecutive stores ≥ 1 day apart), board ≤ ledger, and the state of a restart
(once it saved) holds every cycle the ledger held at that restart.

Run: python bench/write_budget_kills.py [--kills 100] [--seed 1]
"""

from __future__ import annotations

import argparse
import logging
import os
import random
import signal
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from magcal.app import config  # noqa: E402
from magcal.app.daemon import Collaborators, Daemon  # noqa: E402
from magcal.app.daemon.ledger import LEDGER_NAME, read_history  # noqa: E402
from magcal.devices import open_device, simboard  # noqa: E402
from magcal.recordings.state import StateFiles  # noqa: E402

HOUR, DAY = 3600.0, 86400.0
T0 = 1.8e9  # any epoch: only differences matter to the budget


def child(state_dir: Path, boot: int, start_s: float, seed: int) -> None:
    """A forked boot: the daemon on simulated time; never returns."""
    clock = {"t_s": 0.0}
    board_log = state_dir.parent / "board.log"
    real = simboard.SimEeprom.put

    def put(self, offset, payload):
        fd = os.open(board_log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.write(fd, f"{start_s + clock['t_s']:.3f}\n".encode())
        os.fsync(fd)
        os.close(fd)
        real(self, offset, payload)

    simboard.SimEeprom.put = put
    logging.disable(logging.WARNING)  # the table is the report
    port = f"sim://?pace=0&eeprom={state_dir.parent}/eeprom.bin"  # one device, as the unit names it
    settings = config.load(None, {"port": port, "rate_hz": 100, "daemon": {
        "state_every_s": 0.05, "socket": False, "recalibrate": True, "keep": "tracker",
        "write_budget_per_day": 1, "write_burst": 1}}, environ={})
    try:
        Daemon(settings, state_dir=state_dir, collaborators=Collaborators(
            open_device=lambda url, **kw: open_device(f"{url}&seed={seed * 1000 + boot}", **kw),
            wall=lambda: start_s + clock["t_s"],
            on_sample=lambda _e, s: clock.__setitem__("t_s", s.t_s))).run()
    finally:
        os._exit(0)


def board_stores(path: Path) -> list[float]:
    try:
        return [float(x) for x in path.read_text().split()]
    except FileNotFoundError:
        return []


def state_cycles(state_dir: Path) -> tuple[int, int | None]:
    """(the state's generation, the EEPROM cycles it says were spent); (0, None) for none."""
    try:
        data = StateFiles(state_dir).load()
    except Exception:  # a refused state is reported as none
        return 0, None
    keeping = (data or {}).get("resume", {}).get("keeping")
    return int((data or {}).get("generation", 0)), None if keeping is None else int(keeping["cycles"])


def boot_and_kill(state_dir: Path, boot: int, start_s: float, seed: int, after_store: bool,
                  rng: random.Random) -> str:
    board = state_dir.parent / "board.log"
    before = len(board_stores(board))
    (state_dir.parent / "eeprom.bin").unlink(missing_ok=True)  # a blank board: the tracker writes at once
    pid = os.fork()
    if pid == 0:
        child(state_dir, boot, start_s, seed)
    limit = time.monotonic() + (6.0 if after_store else rng.uniform(0.02, 2.5))
    while time.monotonic() < limit:
        if after_store and len(board_stores(board)) > before:
            break
        if os.waitpid(pid, os.WNOHANG)[0]:
            return "exited"
        time.sleep(0.001)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    return "after store" if after_store and len(board_stores(board)) > before else "random"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        state_dir = Path(tmp) / "state"
        state_dir.mkdir()
        return run(state_dir, args, rng)


def run(state_dir: Path, args, rng: random.Random) -> int:
    start_s, bad, saved = T0, [], 0
    print("| kill | moment | sim day | board stores | ledger commands | state cycles (at its last save) |")
    print("|---|---|---|---|---|---|")
    for boot in range(args.kills):
        ledger_before = read_history(state_dir / LEDGER_NAME, start_s).cycles
        generation_before = state_cycles(state_dir)[0]
        moment = boot_and_kill(state_dir, boot, start_s, args.seed, boot % 3 == 0, rng)
        stores = board_stores(state_dir.parent / "board.log")
        ledger = read_history(state_dir / LEDGER_NAME, start_s).cycles
        generation, cycles = state_cycles(state_dir)
        if len(stores) > ledger:
            bad.append(f"kill {boot}: the board stored {len(stores)}, the ledger holds {ledger}")
        saved += generation != generation_before
        # a restart that saved before it was killed: its state holds at least what the ledger did
        if generation != generation_before and cycles is not None and cycles < ledger_before:
            bad.append(f"kill {boot}: the state says {cycles} cycles after a restart, the ledger {ledger_before}")
        print(f"| {boot} | {moment} | {(start_s - T0) / DAY:.2f} | {len(stores)} | {ledger} | {cycles} |", flush=True)
        start_s += rng.uniform(2 * HOUR, 30 * HOUR)
    print(f"\n{saved} of {args.kills} restarts saved a state before the kill; in each the state held every "
          "EEPROM cycle the ledger held at the restart" if not bad else "")
    return verdict(state_dir, start_s, bad)


def verdict(state_dir: Path, end_s: float, bad: list[str]) -> int:
    stores = sorted(board_stores(state_dir.parent / "board.log"))
    gaps = [b - a for a, b in zip(stores, stores[1:])]
    days = (end_s - T0) / DAY
    worst = max((sum(1 for s in stores if w <= s < w + DAY) for w in stores), default=0)
    print(f"\n{len(stores)} board stores over {days:.1f} simulated days; most in any 24 h: {worst}; "
          f"closest two: {min(gaps, default=float('nan')) / HOUR:.1f} h apart")
    if worst > 1:
        bad.append(f"{worst} board stores within 24 h")
    for line in bad:
        print("OVER:", line)
    print("PASS" if not bad else "FAIL")
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
