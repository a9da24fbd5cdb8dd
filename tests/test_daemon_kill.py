"""kill -9 at random moments of a running daemon, 50 times in a row on one state directory:
every restart finds a valid state (never a torn one), resumes from it, and the state stays
consistent — counts only grow, the session's accumulator holds exactly the samples it counted,
the monitor's windows add up to the samples it was given."""

import json
import os
import random
import signal
import time

import pytest

import magcal.devices.simboard  # noqa: F401  (the sim:// backend, which open_device imports on first use)
from magcal.app import config
from magcal.app.daemon import Collaborators, Daemon
from magcal.devices import open_device
from magcal.logic.monitor import DriftMonitor
from magcal.logic.session import Session
from magcal.recordings.state import StateFiles

ITERATIONS = 50


def _mtime(path) -> int:
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return 0


def _child(state_dir: str, seed: int) -> None:
    # runs in a forked child: the imports are already done (at the top of this module, the
    # daemon's own too: ``magcal.app.daemon`` imports it on first use), so a start costs milliseconds
    port = f"sim://?pace=0&eeprom={state_dir}/eeprom.bin"  # one device; each boot moves through other directions
    settings = config.load(None, {
        "port": port,
        "rate_hz": 100,
        "daemon": {"state_every_s": 0.005, "socket": False, "monitor_window": 200, "recalibrate": True},
    }, environ={})
    try:
        Daemon(settings, state_dir=state_dir, collaborators=Collaborators(
               open_device=lambda url, **kw: open_device(f"{url}&seed={seed}", **kw))).run()
    finally:
        os._exit(0)


def _check(payload: dict, before: dict | None) -> None:
    r = payload["resume"]
    session = Session.from_state(r["session"])
    valid = session.counters["samples_in"] - sum(v for k, v in session.counters.items() if k.startswith("rejected"))
    assert session.accumulator.n == valid
    assert r["samples"] >= session.counters["samples_in"]
    if r["monitor"]:
        mon = DriftMonitor.from_state(r["monitor"])
        assert mon.windows * mon.window + len(r["monitor"]["buffer_ut"]) <= r["samples"]
    if r["last_calibration"]:
        assert r["last_calibration"]["verified"] is True
        assert r["calibration"] is not None
    if before is not None and payload["generation"] == before["generation"]:
        assert payload == before  # killed before it saved anything new: the old state stands
    elif before is not None:
        assert payload["generation"] > before["generation"]
        assert r["samples"] >= before["resume"]["samples"]
        assert r["recalibrations"] >= before["resume"]["recalibrations"]
        assert r["epoch"] > before["resume"]["epoch"]  # it resumed (and connected again)


@pytest.mark.slow
def test_kill_9_at_random_points_always_resumes(tmp_path):
    if not hasattr(os, "fork"):  # a real platform condition (Windows); never skipped in CI
        if os.environ.get("CI") == "true":
            pytest.fail("fork() is required in CI")
        pytest.skip("needs fork()")
    rng = random.Random(20261122)
    store = StateFiles(tmp_path)
    before = None
    resumed = 0
    for i in range(ITERATIONS):
        mtime = _mtime(store.current)
        pid = os.fork()
        if pid == 0:
            _child(str(tmp_path), seed=1 + i)
        if rng.random() < 0.75:  # mostly after this run has saved at least once, at any point later
            end = time.monotonic() + 20
            while _mtime(store.current) == mtime and time.monotonic() < end:
                time.sleep(0.002)
            time.sleep(rng.uniform(0.0, 0.25))
        else:  # anywhere, also during start-up or the very first write
            time.sleep(rng.uniform(0.0, 0.3))
        os.kill(pid, signal.SIGKILL)
        _, status = os.waitpid(pid, 0)
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, "the daemon died on its own"
        payload = store.load()  # raises StateError on a torn or invalid file
        if payload is None:
            continue  # killed before its first save
        _check(payload, before)
        if before is not None and payload["generation"] > before["generation"]:
            resumed += 1
        before = payload
    assert resumed >= ITERATIONS // 2  # most kills came after the restart had saved again
    assert before["resume"]["samples"] > 0
    # a calibration was written, verified and kept: either this state counted the write, or a
    # kill fell between the verified write and the next save, and the restarted daemon read the
    # calibration back from the board (it never recalibrates over a good one)
    assert before["resume"]["recalibrations"] >= 1 or before["status"]["calibration"], json.dumps(before["status"])
    print(f"\n{resumed} of {ITERATIONS} kills came after a resumed save; final state: generation "
          f"{before['generation']}, {before['resume']['samples']} samples, epoch {before['resume']['epoch']}")
    leftovers = [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    assert len(leftovers) <= ITERATIONS  # stray temp files from kills mid-write are only ignored
