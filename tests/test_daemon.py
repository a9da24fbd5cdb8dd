"""The daemon under injected faults, as a user would see it: it keeps running, every sample the
device sent reaches it exactly once and in order (sequence numbers and raw values compared with
what the simulated board emitted), and a calibration that failed a gate or was not verified by
read-back is never reported (and the previous one is put back)."""

import itertools
import threading

import numpy as np
import pytest

from magcal.app import config
from magcal.app.daemon import Collaborators, Daemon, Decision, Stop
from magcal.devices import open_device, parse_port
from magcal.devices.base import read_to_end
from magcal.devices.fakebus import FakeClock
from magcal.devices.simboard import SimBoard
from magcal.recordings.state import StateFiles
from magcal.wire.protocol import record_from_calibration


WALL_LIMIT_S = 300.0


def make_settings(port, **daemon):
    d = {"reconnect_min_s": 0.01, "reconnect_max_s": 0.05, "stall_s": 0.3, "state_every_s": 0.2,
         "monitor_window": 200, "socket": False}
    d.update(daemon)
    return config.load(None, {"port": port, "rate_hz": 100, "daemon": d}, environ={})


class Tracked:
    """A sim board whose every emitted sample line is logged, and the daemon's view. Every
    daemon run here connects to this one board (as one would replug one real board)."""

    def __init__(self, query):
        self.url = f"sim://?pace=0&{query}"
        self.board = SimBoard.from_port(parse_port(self.url))
        self.emitted = []
        emit = self.board._emit

        def logging_emit(kind, *fields):
            if kind == "S":
                self.emitted.append((self.board._seq, tuple(fields[1:4])))
            emit(kind, *fields)

        self.board._emit = logging_emit
        self.collected = []

    def options(self, **more):
        return {"board": self.board, **more}

    def on_sample(self, epoch, s):
        self.collected.append((epoch, s.seq, s.raw))

    def run(self, tmp_path, samples, device_clock=None, **daemon):
        settings = make_settings(self.url, **daemon)
        opener = open_device if device_clock is None else _opened_on(device_clock)
        d = Daemon(settings, state_dir=tmp_path / "state", max_samples=samples,
                   collaborators=Collaborators(open_device=opener, on_sample=self.on_sample,
                                               device_options=self.options(reply_timeout_s=0.25)))
        # a daemon that cannot reach its sample count (a board that stopped answering is retried
        # for ever, as it should be) fails here instead of hanging the suite
        guard = threading.Timer(WALL_LIMIT_S, d.request_stop)
        guard.start()
        try:
            assert d.run() == 0
        finally:
            guard.cancel()
        assert d.stopped_by is not Stop.REQUESTED, f"not done after {WALL_LIMIT_S} s: {d.journal.decisions()[-5:]}"
        return d

    def assert_exactly_once(self):
        got = [(seq, raw) for _, seq, raw in self.collected]
        assert got == self.emitted[: len(got)], "a sample was lost, duplicated or reordered"
        unread = bytes(self.board._out).count(b"$S,")
        assert len(self.emitted) - len(got) == unread
        # within one epoch the sequence numbers only go forward (modulo 2¹⁶)
        for epoch, group in itertools.groupby(self.collected, key=lambda c: c[0]):
            seqs = [c[1] for c in group]
            assert all(0 < (b - a) % 65536 < 32768 for a, b in zip(seqs, seqs[1:])), f"sequence went back in epoch {epoch}"


class LookClock:
    """A device's clock of its own that moves on ``step_s`` each time it is read, not with the
    wall: a reply timeout is then a fixed number of looks at the link, the same on an idle
    machine and a loaded one. A reply the board sent is read at the first look (it answers a
    command at once), so only a board that never answers waits the timeout out — in two looks
    (0.25 s at 0.1 s a look) instead of a wall-clock 0.25 s in which the unpaced board streams
    thousands of lines that the daemon then has to take in."""

    def __init__(self, step_s: float = 0.1):
        self.step_s, self.t_s = step_s, 0.0

    def __call__(self) -> float:
        self.t_s += self.step_s
        return self.t_s


def _opened_on(clock):
    """``open_device`` whose device keeps time by ``clock`` (its reply and read timeouts)."""

    def opened(url, **options):
        dev = open_device(url, **options)
        dev.clock = clock
        return dev

    return opened


def within(value, bounds) -> bool:
    lo, hi = bounds
    return lo <= value and (hi is None or value <= hi)


# a fault of the link, what the daemon must count (lowest, highest; None: no upper bound)
# and the epochs it must end in (each connection and each device reset is one)
LINK_FAULTS = {
    # unplugged twice: reconnected each time; the port was still gone at the first retry
    "unplug": ("seed=3&fault=unplug@3+0.2&fault=unplug@6+0.05", 1000,
               {"port_lost": (2, 2), "connect_failed": (1, None)}, (3, 3)),
    # a silent link is noticed and reopened
    "stall": ("seed=4&fault=stall@2+0.6", 500, {"stalls": (1, 1)}, (2, None)),
    # a reset mid-line: streaming is started again after it
    "reset": ("seed=5&fault=reset@2", 600, {"device_resets": (1, 1)}, (2, 2)),
}


@pytest.mark.parametrize("fault", list(LINK_FAULTS))
def test_a_link_fault_is_survived_and_no_sample_is_lost(tmp_path, fault):
    query, samples, counts, epochs = LINK_FAULTS[fault]
    t = Tracked(query)
    d = t.run(tmp_path, samples)
    assert all(within(d.faults[k], b) for k, b in counts.items()), dict(d.faults)
    assert within(d.intake.epoch, epochs), d.intake.epoch
    assert d.intake.samples >= samples
    t.assert_exactly_once()


def test_garbage_bursts_are_counted_and_lose_no_sample(tmp_path):
    t = Tracked("seed=6&fault=garbage@1=400&fault=garbage@2.5=2000&fault=garbage@4=50")
    d = t.run(tmp_path, 600)
    assert d.intake.samples >= 600
    t.assert_exactly_once()
    # the framer counted the noise (the device object is closed; its counters went to the log)
    assert Decision.CONNECTED in d.journal.decisions()


def _stored_record(board):
    status, values = board.eeprom.load_record()
    return status, values


def _calibrated_then(tmp_path, faults, samples=12500):
    """Blank board, recalibration on: the daemon calibrates, then a payload adds hard iron at
    t = 50 s together with ``faults``."""
    t = Tracked(f"seed=7&fault=hard_iron@50=30.5,-38.2,14.8{faults}")
    # the alarm path (the tracker's: test_daemon_keeping); a stall limit no loaded machine reaches
    # by accident (a spurious reconnect after the board went mute can never identify it again);
    # the device keeps time by looks (LookClock): a command the board never answers times out
    # after two looks at the link, not after 0.25 s of lines the unpaced board streams meanwhile
    d = t.run(tmp_path, samples, device_clock=LookClock(), recalibrate=True, keep="alarm", stall_s=3.0)
    t.assert_exactly_once()
    return t, d


@pytest.mark.slow
def test_new_hard_iron_is_detected_and_recalibrated(tmp_path):
    t, d = _calibrated_then(tmp_path, "")
    assert d.writer.count == 2  # the first one on a blank board, then after the payload
    assert d.faults["drift_alarms"] >= 1
    np.testing.assert_allclose(d.drift.calibration.offset_ut, [30.5, -38.2, 14.8], atol=0.6)
    status, values = _stored_record(t.board)
    assert status == "OK" and values == record_from_calibration(d.drift.calibration)
    assert d.writer.last["verified"] is True
    assert Decision.DRIFTED in d.journal.decisions()


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["mute", "no_write_ack", "corrupt_write"])
def test_a_write_that_is_not_verified_is_never_reported(tmp_path, fault):
    t, d = _calibrated_then(tmp_path, f"&fault={fault}@50")
    assert d.writer.count == 1  # the first calibration succeeded before the fault
    assert d.faults["drift_alarms"] >= 1
    assert Decision.NOT_WRITTEN in d.journal.decisions()
    # what the daemon reports is the calibration it verified, and the device still holds it
    status, values = _stored_record(t.board)
    assert status == "OK" and values == record_from_calibration(d.drift.calibration)
    assert np.linalg.norm(d.drift.calibration.offset_ut - np.array([23.5, -41.2, 12.8])) < 1.0
    assert d.writer.last["calibration"] == d.drift.calibration.to_dict()


@pytest.mark.slow
def test_a_calibration_failing_a_gate_is_never_written(tmp_path):
    t = Tracked("seed=8")
    settings = config.load(None, {"port": t.url, "gates": {"max_rms_ut": 0.05},
                                  "daemon": {"recalibrate": True, "socket": False, "monitor_window": 200}},
                           environ={})
    d = Daemon(settings, state_dir=tmp_path, max_samples=4000,
               collaborators=Collaborators(on_sample=t.on_sample, device_options=t.options()))
    d.run()
    assert d.writer.count == 0 and d.writer.last is None and d.drift.calibration is None
    assert _stored_record(t.board)[0] == "BLANK"
    t.assert_exactly_once()


def test_full_disk_for_captures_keeps_streaming(tmp_path, monkeypatch):
    import errno

    from magcal.recordings import capture

    t = Tracked("seed=9")
    real_append = capture.CaptureWriter.append
    calls = {"n": 0}

    def append(self, data, t_rx_s=None):
        calls["n"] += 1
        if calls["n"] == 20:  # the disk fills up mid-run
            self._fail(OSError(errno.ENOSPC, "No space left on device"), len(data))
            return False
        return real_append(self, data, t_rx_s)

    monkeypatch.setattr(capture.CaptureWriter, "append", append)
    d = t.run(tmp_path, 1500, capture_max_bytes=1 << 20)
    assert d.faults["capture_failed"] == 1, (calls, d.faults, list(d.journal.entries))
    assert d.intake.samples >= 1500
    t.assert_exactly_once()
    assert "disk full" in d.capture.stats()["error"]


def test_a_disk_that_fills_as_the_daemon_stops_is_reported_and_the_stop_completes(tmp_path, monkeypatch):
    """The capture has just failed (disk full) when the daemon sends its stop command, so the
    failure surfaces while the stop waits for its reply: it is counted once, the stop asked
    again, every sample already received handed over, and the daemon exits 0."""
    import errno

    from magcal.devices.protocol_client import ProtocolDevice

    t = Tracked("seed=9")
    real_stop = ProtocolDevice._stop
    filled = []

    def stop(self):
        if not filled:
            filled.append(True)
            self.transport.writer._fail(OSError(errno.ENOSPC, "No space left on device"), 0)
        return real_stop(self)

    monkeypatch.setattr(ProtocolDevice, "_stop", stop)
    d = t.run(tmp_path, 600, capture_max_bytes=1 << 20)
    assert filled, "the daemon never stopped the device: the test checked nothing"
    assert d.faults["capture_failed"] == 1
    assert "disk full" in d.capture.stats()["error"]
    t.assert_exactly_once()


@pytest.mark.slow
def test_rolling_capture_stays_within_its_bound(tmp_path):
    t = Tracked("seed=10")
    d = t.run(tmp_path, 3000, capture_max_bytes=40_000)
    files = list((tmp_path / "state").glob("capture.cap*"))
    assert 1 <= len(files) <= 2
    assert sum(f.stat().st_size for f in files) <= 40_000
    assert d.capture.stats()["rolls"] >= 1


def test_restart_resumes_the_accumulated_state(tmp_path):
    t = Tracked("seed=11")
    a = t.run(tmp_path, 800)
    saved = StateFiles(tmp_path / "state").load()
    assert saved["resume"]["samples"] == a.intake.samples
    b = t.run(tmp_path, a.intake.samples + 500)
    assert b.intake.samples >= a.intake.samples + 500
    session = b.recalibrator.session
    assert session.accumulator.n == session.counters["samples_in"]  # nothing counted twice
    assert session.counters["samples_in"] == b.intake.samples  # the session spans both runs
    assert Decision.RESUMED in b.journal.decisions()
    assert b.keeper.generation > a.keeper.generation


def test_state_of_another_port_is_not_mixed_in(tmp_path):
    t = Tracked("seed=14")
    a = t.run(tmp_path, 700)
    other = Daemon(make_settings("sim://?pace=0&seed=15"), state_dir=tmp_path / "state")
    other.resume()
    assert other.recalibrator.session.accumulator.n == 0 and other.drift.monitor is None
    assert other.intake.samples == a.intake.samples  # the counters go on
    assert Decision.STATE_OTHER_PORT in other.journal.decisions()


def test_torn_state_file_falls_back_to_the_previous_one(tmp_path):
    t = Tracked("seed=12")
    a = t.run(tmp_path, 600, state_every_s=0.01)
    store = StateFiles(tmp_path / "state")
    blob = store.current.read_bytes()
    store.current.write_bytes(blob[: len(blob) // 3])
    b = Daemon(make_settings(t.url), state_dir=tmp_path / "state", max_samples=a.intake.samples + 100)
    b.resume()
    assert 0 < b.intake.samples <= a.intake.samples
    assert b.keeper.loaded_from == "state.prev.json"  # state.json was refused
    assert [e["source"] for e in b.journal.find(Decision.RESUMED)][-1] == "state.prev.json"


def test_reload_rejects_an_invalid_config_and_keeps_the_old(tmp_path):
    cfg = tmp_path / "magcal.yaml"
    cfg.write_text("daemon:\n  monitor_alpha: 0.01\n")
    settings = config.load(str(cfg), environ={})
    d = Daemon(settings, state_dir=tmp_path, config_path=str(cfg))
    cfg.write_text("daemon:\n  monitor_alpha: 2\n")
    d.reload()
    assert d.settings.daemon.monitor_alpha == 0.01
    assert d.faults["config_rejected"] == 1
    cfg.write_text("daemon:\n  monitor_alpha: 0.002\n")
    d.reload()
    assert d.settings.daemon.monitor_alpha == 0.002


def _record_capture(path, seconds=12.0, seed=13):
    """A capture of a sim board streaming at 100 Hz, chunks stamped with the board's time."""
    from magcal.devices.simboard import SimBoard
    from magcal.recordings.capture import CaptureWriter, make_header
    from magcal.sim.physics import demo_scenario
    from magcal.wire.protocol import encode_command

    board = SimBoard(demo_scenario(seed), rate_hz=100)
    w = CaptureWriter(path, make_header("sim://", 115200))
    board.write(encode_command("G", 1))
    while board._t_s < seconds:
        w.append(board.read(700), t_rx_s=board._t_s)
    w.close()


def test_replay_faults_keep_every_recorded_sample_once(tmp_path):
    cap = tmp_path / "run.cap"
    _record_capture(cap)
    clean = [(s.seq, s.raw) for s in read_to_end(open_device(f"replay://{cap}")) if s.valid]
    # the link, its faults, the device and the daemon keep one fake clock: a stall lasts its
    # stated time however long the daemon takes over the samples before it
    url = (f"replay://{cap}?fault=unplug@3+0.4&fault=stall@5+0.5&fault=garbage@7=500"
           f"&fault=reset@8&fault=unplug@10+0.4")
    got = []
    clock = FakeClock()
    d = Daemon(make_settings(url), state_dir=tmp_path / "state",
               collaborators=Collaborators(device_options={"clock": clock, "sleep": clock.sleep}, clock=clock,
                                           sleep=clock.sleep, on_sample=lambda e, s: got.append((s.seq, s.raw))))
    assert d.run() == 0
    assert d.stopped_by is Stop.SOURCE_ENDED
    assert got == clean
    assert d.faults["port_lost"] == 2, (d.faults, list(d.journal.entries))
    assert d.faults["stalls"] == 1
    assert d.faults["device_resets"] == 1


def test_a_restarted_daemon_resumes_a_replay_where_it_stopped(tmp_path):
    """A replay is read from its start each time it is opened; a daemon restarted on the same
    state must not feed the lines it already took into the resumed session a second time."""
    cap = tmp_path / "run.cap"
    _record_capture(cap)
    recorded = read_to_end(open_device(f"replay://{cap}"))
    clean = [(s.seq, s.raw) for s in recorded if s.valid]
    url = f"replay://{cap}"
    got = []
    first = Daemon(make_settings(url), state_dir=tmp_path / "state", max_samples=len(clean) // 3,
                   collaborators=Collaborators(on_sample=lambda e, s: got.append((s.seq, s.raw))))
    assert first.run() == 0
    taken = len(got)
    assert 0 < taken < len(clean)
    second = Daemon(make_settings(url), state_dir=tmp_path / "state",
                    collaborators=Collaborators(on_sample=lambda e, s: got.append((s.seq, s.raw))))
    assert second.run() == 0
    assert second.stopped_by is Stop.SOURCE_ENDED
    assert got == clean  # every recorded sample once, in order, across the restart
    assert second.intake.samples == len(clean)
    assert second.recalibrator.session.progress()["samples"] == len(recorded)  # the resumed session took each line once
    assert [e["skipped_lines"] for e in second.journal.find(Decision.REPLAY_SKIPS)] == [taken]


def test_a_second_daemon_on_the_same_state_dir_is_refused(tmp_path):
    import threading

    from magcal.core.errors import StateError

    first = Daemon(make_settings("sim://?seed=16&pace=5"), state_dir=tmp_path)
    th = threading.Thread(target=first.run)
    th.start()
    try:
        import time

        end = time.monotonic() + 20
        while first.intake.samples == 0 and time.monotonic() < end:
            time.sleep(0.02)
        second = Daemon(make_settings("sim://?pace=0&seed=16"), state_dir=tmp_path)
        with pytest.raises(StateError, match="another magcal daemon"):
            second.run()
    finally:
        first.request_stop()
        th.join(10)
    assert not th.is_alive()
    assert StateFiles(tmp_path).load()["resume"]["samples"] == first.intake.samples  # its state is intact


def test_the_daemon_keeps_a_capture_of_a_motioncal_board_that_replays_to_the_same_readings(tmp_path):
    from adafruit_device import AdafruitBoard

    got = []
    with AdafruitBoard(lines_per_s=1000, seed=4) as board:
        settings = config.load(None, {"port": board.port, "dialect": "motioncal", "rate_hz": 100,
                                      "daemon": {"stall_s": 2.0, "state_every_s": 0.5, "socket": False,
                                                 "capture_max_bytes": 10_000_000}}, environ={})
        d = Daemon(settings, state_dir=tmp_path / "state", max_samples=500,
                   collaborators=Collaborators(on_sample=lambda e, s: got.append(s.field_ut)))
        assert d.run() == 0
    cap = tmp_path / "state" / "capture.cap"
    replayed = [s.field_ut for s in read_to_end(open_device(f"replay://{cap}"))]
    assert len(got) >= 500 and replayed[: len(got)] == got


@pytest.mark.parametrize("kind", ["binary", "nested", "int_key", "null_key", "range_3", "directory", "baud_sim",
                                  "bad_port", "nan"])
def test_a_bad_config_on_reload_keeps_the_running_settings(tmp_path, kind):
    """SIGHUP with a bad config killed the daemon (exit 1) for four of these; now each is
    rejected, counted and logged, and the daemon goes on with what it had."""
    cfg = tmp_path / "magcal.yaml"
    cfg.write_text("daemon:\n  monitor_alpha: 0.01\n")
    settings = config.load(str(cfg), {"port": "sim://?pace=0"}, environ={})
    d = Daemon(settings, state_dir=tmp_path / "state", config_path=str(cfg), overrides={"port": "sim://?pace=0"})
    bad = {
        "binary": bytes(range(256)), "nested": b"gates: " + b"[" * 50_000 + b"]" * 50_000,
        "int_key": b"1: 2\n", "null_key": b"~: 2\n", "range_3": b"gates:\n  field_range_ut: [1, 2, 3]\n",
        "baud_sim": b"baud: 9600\ndaemon:\n  monitor_alpha: 0.02\n", "bad_port": b"port: sim://?seed=x\n",
        "nan": b"daemon:\n  state_every_s: .nan\n",
    }
    if kind == "directory":
        cfg.unlink()
        cfg.mkdir()
    elif kind == "bad_port":
        d.overrides = {}  # the port from the file this time
        cfg.write_bytes(bad[kind])
    else:
        cfg.write_bytes(bad[kind])
    d.reload()
    if kind == "baud_sim":  # not an error: a serial-port setting a simulated board has no use for
        assert d.settings.daemon.monitor_alpha == 0.02 and d.faults["config_rejected"] == 0
        return
    assert d.settings is settings and d.faults["config_rejected"] == 1
    (rejected,) = d.journal.find(Decision.RELOAD_REJECTED)
    assert (str(cfg) in rejected["error"]) != (kind == "bad_port") and "\n" not in rejected["error"]


def test_a_stopped_daemon_gives_back_the_signals_it_took(tmp_path):
    """Run in-process (a test, an embedding program): once run() returns, SIGTERM, SIGINT and
    SIGHUP go where they went before — not to a stopped daemon that would swallow a Ctrl-C."""
    import signal

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    Tracked("seed=3").run(tmp_path, 300)
    assert {s: signal.getsignal(s) for s in before} == before
