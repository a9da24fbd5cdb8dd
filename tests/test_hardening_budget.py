"""The EEPROM write budget survives kill -9: every write is recorded in the write ledger before
it is sent, an unresolved one counts as spent at the next start, and the budget is charged from
the ledger — so no kill, at any moment, lets the daemon wear the EEPROM past its budget."""

import json
import os
import signal
import time

import pytest
from forked_magcal import Launcher

from magcal.app import config
from magcal.app.daemon import Daemon, Decision
from magcal.app.daemon.ledger import LEDGER_NAME, LedgeredDevice, WriteLedger, read_history
from magcal.logic.keeper import DAY_S, Budget, Keeper
from magcal.logic.gates import Gates
from magcal.recordings.state import StateFiles

# the real ``magcal run``, with the simulated board's every EEPROM store counted first (fsynced
# before the store, so the count is never below what the board took, whatever the kill); each
# boot a process of its own, forked by a launcher that imported magcal once (forked_magcal)
PATCH = """
import os
import magcal.app.daemon, magcal.cli.run  # what `magcal run` imports, imported once for every boot
import magcal.app.daemon.daemon  # the daemon itself (scipy.stats …), which run imports on first use
from magcal.devices import simboard
real = simboard.SimEeprom.put
def put(self, offset, payload):
    fd = os.open(os.environ["BOARD_LOG"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.write(fd, b"put\\n"); os.fsync(fd); os.close(fd)
    real(self, offset, payload)
simboard.SimEeprom.put = put
"""


def _lines(path) -> int:
    try:
        return len(path.read_bytes().splitlines())
    except FileNotFoundError:
        return 0


def _intents(state_dir) -> int:
    return read_history(state_dir / LEDGER_NAME, time.time()).cycles


def _refusals(state_dir):
    """How many times the daemon reached a write it wanted (gates passed, significantly better)
    and found the budget spent, as its state file says (saved every ``state_every_s``); read
    again only when the file changed."""
    seen = {"mtime": None, "count": 0}

    def count() -> int:
        try:
            mtime = StateFiles(state_dir).current.stat().st_mtime_ns
        except FileNotFoundError:
            return 0
        if mtime != seen["mtime"]:
            payload = StateFiles(state_dir).load()
            seen["mtime"], seen["count"] = mtime, payload["status"]["faults"].get("write_budget_waits", 0)
        return seen["count"]

    return count


def _start(launcher: Launcher, tmp_path, offset: str, count: int | None = None) -> int:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("daemon:\n  write_budget_per_day: 1\n  write_burst: 1\n  socket: false\n  state_every_s: 0.2\n")
    port = f"sim://?pace=0&eeprom={tmp_path}/ee.bin&offset={offset}"
    argv = ["run", "--port", port, "--config", str(cfg), "--state-dir", str(tmp_path / "st"), "--recalibrate",
            "--log-level", "WARNING"]
    return launcher.start(argv + (["--count", str(count)] if count else []), stderr=tmp_path / "err.txt")


def _kill_when(launcher: Launcher, pid: int, grew, limit_s: float) -> None:
    """SIGKILL as soon as ``grew()`` is true, or after ``limit_s``."""
    end = time.monotonic() + limit_s
    while time.monotonic() < end and not grew():
        if launcher.poll(pid) is not None:
            return  # it ended on its own (and is reaped)
        time.sleep(0.002)
    os.kill(pid, signal.SIGKILL)
    launcher.wait(pid, timeout_s=10)


@pytest.mark.slow
def test_kill_9_around_writes_never_exceeds_the_budget(tmp_path):
    """Budget 1 a day, burst 1: six boots of ``magcal run``, each against a board whose hard
    iron moved (the tracker wants to write every time), killed at a random moment, right after
    the ledger's intent, or right after the board's store — or, where the budget is spent, right
    after the write it wanted was refused. The board stores once in all.

    Each moment is one of the command's life: a boot no longer pays the interpreter's start-up
    and imports (the launcher paid them once, ``startup_s``), so every wait, counted from the
    fork, is the one a fresh ``python -m magcal`` had left after them."""
    st, board = tmp_path / "st", tmp_path / "board.log"
    moments = ["store", "intent", "random", "store", "intent", "random"]
    env = {**os.environ, "BOARD_LOG": str(board), "MAGCAL_CONFIG": ""}
    with Launcher(PATCH, env) as launcher:
        def after_startup(s: float) -> float:
            return max(0.0, s - launcher.startup_s)

        for i, moment in enumerate(moments):
            before_board, before_intents = _lines(board), _intents(st)
            refusals = _refusals(st)
            before_refusals = refusals()
            pid = _start(launcher, tmp_path, f"{10 + 7 * i},-20,{5 * i}")
            if moment == "random":
                _kill_when(launcher, pid, lambda: False, after_startup(0.8 + 0.4 * i))
            else:
                # killed right after the store (the intent); a boot that finds the budget spent
                # never makes either, and is killed once it reached the write it wanted and the
                # budget refused it. Every boot is given all the time it needs to get there (on a
                # loaded machine seconds can pass first, and the boot would then test nothing):
                # the first must store once, every later one finds the budget spent.
                made = (lambda: _lines(board) > before_board) if moment == "store" else (
                    lambda: _intents(st) > before_intents)
                _kill_when(launcher, pid, lambda: made() or refusals() > before_refusals, 60.0)
                assert made() or refusals() > before_refusals, f"boot {i} ({moment}) never reached a write"
                assert i > 0 or _lines(board) == 1, "the first boot never reached its store"
            assert _lines(board) <= _intents(st)  # every store the board took was recorded first
            assert _lines(board) <= 1, f"boot {i} ({moment}): the board stored {_lines(board)} times"
        pid = _start(launcher, tmp_path, "40,-20,30", count=2500)  # a clean run: it resumes, then says what it counts
        code = launcher.wait(pid, timeout_s=60)
    assert code == 0, (tmp_path / "err.txt").read_text()[-2000:]
    keeping = StateFiles(st).load()["resume"]["keeping"]
    assert keeping["cycles"] == _intents(st) >= _lines(board) == 1
    assert keeping["tokens"] < 1.0


def _keeper() -> Keeper:
    return Keeper(Gates(), Budget(per_day=1, burst=1))


def test_the_ledger_charges_what_the_state_missed():
    """A state saved before the write knew nothing of it; the ledger charges it all the same,
    and its counts become the keeper's."""
    k = _keeper()
    k.charge_history([1000.0], writes=1, failed=0)
    assert not k.affords(1000.0 + 0.5 * DAY_S)
    assert k.affords(1000.0 + DAY_S)
    assert (k.cycles, k.writes) == (1, 1)


def test_an_unresolved_intent_counts_as_spent(tmp_path):
    """A process killed between the intent and the resolution: at the next open the write is
    counted (spent, not verified) and resolved as interrupted."""
    led = WriteLedger(tmp_path, lambda: 5000.0)
    led.open()
    led.intent(led.begin(), "write")
    led.close()
    again = WriteLedger(tmp_path, lambda: 5001.0)
    h = again.open()
    assert (h.cycles, h.verified, h.failed, h.unresolved) == (1, 0, 1, [1])
    again.close()
    h2 = read_history(tmp_path / LEDGER_NAME, 5002.0)
    assert (h2.cycles, h2.unresolved, h2.not_verified) == (1, [], 1)


def test_a_torn_ledger_line_counts_as_a_write(tmp_path):
    (tmp_path / LEDGER_NAME).write_bytes(b'{"op":1,"intent":"write","t_utc":10.0}\n{"op":1,"res')
    h = read_history(tmp_path / LEDGER_NAME, 99.0)
    assert h.spent_at_s == [10.0, 99.0]


def test_a_ledger_behind_a_link_is_not_opened(tmp_path):
    target = tmp_path / "elsewhere"
    target.write_text("keep me\n")
    (tmp_path / LEDGER_NAME).symlink_to(target)
    led = WriteLedger(tmp_path, lambda: 1.0)
    with pytest.raises(Exception, match="cannot be opened"):
        led.open()
    assert target.read_text() == "keep me\n"


class _Board:
    """Counts the stores it is asked for, and what the ledger held at each."""

    def __init__(self, ledger_path):
        self.path, self.seen = ledger_path, []

    def write_calibration(self, cal):
        self.seen.append(_lines(self.path))
        return cal


def test_the_intent_is_on_disk_before_the_command(tmp_path):
    led = WriteLedger(tmp_path, lambda: 7.0)
    led.open()
    board = _Board(led.path)
    dev = LedgeredDevice(board, led)
    dev.write_calibration("first")
    dev.write_calibration("previous put back")
    assert board.seen == [1, 2]
    assert dev.resolve(verified=False) == 2
    entries = [json.loads(x) for x in led.path.read_text().splitlines()]
    assert [e.get("intent") or e.get("resolved") for e in entries] == ["write", "restore", "not_verified"]


def test_a_daemon_resumes_the_ledger_into_its_state(tmp_path):
    """A ledger holding a write the state never heard of: the daemon's first save says it."""
    st = tmp_path / "st"
    st.mkdir()
    (st / LEDGER_NAME).write_text('{"op":4,"intent":"write","t_utc":%f}\n' % time.time())
    settings = config.load(None, {"port": "sim://?pace=0", "daemon": {"socket": False}}, environ={})
    d = Daemon(settings, state_dir=st, max_samples=1)
    d.run()
    keeping = StateFiles(st).load()["resume"]["keeping"]
    assert (keeping["cycles"], keeping["failed"]) == (1, 1)
    assert Decision.WRITE_INTERRUPTED in d.journal.decisions()


def test_the_recalibrator_s_writes_are_charged_to_the_same_budget(tmp_path):
    """``daemon.keep: alarm`` writes a refit after the monitor rings: within the same budget,
    from the same ledger."""
    st = tmp_path / "st"
    st.mkdir()
    (st / LEDGER_NAME).write_text('{"op":1,"intent":"write","t_utc":%f}\n{"op":1,"resolved":"verified","t_utc":%f}\n'
                                  % (time.time() - 60, time.time() - 59))
    settings = config.load(None, {"port": "sim://?pace=0", "daemon": {
        "socket": False, "keep": "alarm", "write_budget_per_day": 1, "write_burst": 1}}, environ={})
    d = Daemon(settings, state_dir=st, max_samples=1)
    d.tracking.open_ledger()
    try:
        assert not d.tracking.may_spend()
        assert d._write(session=None) is None
        assert d.journal.decisions()[-1] is Decision.BUDGET_WAIT
    finally:
        d.tracking.close_ledger()
