"""The daemon's collaborators, each alone: what a user of ``magcal run`` relies on, one room at a
time (the whole daemon under faults is tests/test_daemon.py)."""

from __future__ import annotations

import threading
from collections import Counter

import pytest

from magcal.app import config
from magcal.app.daemon.control import ControlSocket, query_socket
from magcal.app.daemon.drift import DriftWatcher
from magcal.app.daemon.intake import Intake, Take
from magcal.app.daemon.journal import Decision, Journal
from magcal.app.daemon.persistence import Saved, StateDirLock, StateKeeper
from magcal.app.daemon.recalibrator import READY_EVERY, CalibrationWriter, Recalibrator
from magcal.app.daemon.supervisor import LinkSupervisor
from magcal.core.errors import PortError, StateError
from magcal.core.events import Event
from magcal.core.sample import Sample
from magcal.devices import open_device
from magcal.devices.base import batches


def settings(port="sim://?pace=0&seed=2", **daemon):
    d = {"reconnect_min_s": 0.5, "reconnect_max_s": 4.0, "stall_s": 1.0, "socket": False, "monitor_window": 200}
    d.update(daemon)
    return config.load(None, {"port": port, "rate_hz": 100, "daemon": d}, environ={})


def journal():
    return Journal(lambda: 1e9, position=lambda: 0)


def sample(seq, valid=True, **aux):
    return Sample(seq=seq, t_s=seq / 100, field_ut=(20.0, 0.0, 40.0), st2=0 if valid else 0x08, aux=aux)


def test_the_journal_keeps_decisions_typed_and_says_them_in_words(caplog):
    j = journal()
    with caplog.at_level("WARNING", logger="magcal.daemon"):
        e = j.record(Decision.LINK_LOST, why="link lost: unplugged")
    assert e["decision"] == "link_lost" and e["what"] == "disconnected" and e["why"] == "link lost: unplugged"
    assert "disconnected why=link lost: unplugged" in caplog.text
    j.restore([{"what": "an entry from an older state"}])
    assert j.decisions() == [Decision.LINK_LOST] and len(j.entries) == 2
    assert j.find(Decision.LINK_LOST) == [e]


def test_intake_takes_each_line_once_and_skips_what_a_resumed_replay_already_took():
    i = Intake()
    i.new_epoch()
    assert [i.take(s) for s in (sample(1), sample(1), sample(2, valid=False), sample(3, calibrated=1.0))] == [
        Take.GOOD, Take.DUPLICATE, Take.UNUSABLE, Take.UNUSABLE]
    assert (i.samples, i.samples_in, i.epoch) == (1, 4, 1)
    i.new_epoch()
    assert i.take(sample(1)) is Take.GOOD  # sequence numbers start over in a new epoch
    j = Intake()
    j.skip_replayed(2)
    items = [sample(1), Event("gap", seq=2, count=1), sample(2), sample(3)]
    assert list(j.admit(items, replay=True)) == [sample(3)]
    assert j.replay_lines == 3


def test_the_link_supervisor_backs_off_doubling_to_its_bound_and_drops_a_stalled_link():
    now = [0.0]
    faults = Counter()
    j = journal()
    link = LinkSupervisor(settings("sim://?pace=0&seed=2&fault=unplug+60"), j, faults, open_device=open_device,
                          clock=lambda: now[0])
    waits = []
    for _ in range(5):
        assert link.connect() is None  # unplugged from power-up
        waits.append(link.backoff_s())
    assert waits == [0.5, 1.0, 2.0, 4.0, 4.0] and faults["connect_failed"] == 5
    assert j.decisions() == [Decision.CONNECT_FAILED] * 5

    ok = LinkSupervisor(settings(), journal(), faults, open_device=open_device, clock=lambda: now[0])
    conn = ok.connect()
    assert conn.identity.wia == 0x48 and conn.stored is None and ok.connected
    assert [i for i in ok.read(0.2) if isinstance(i, Sample)]
    ok.heard()
    now[0] += 0.9
    assert not ok.stalled(now[0])
    now[0] += 0.2
    assert ok.stalled(now[0]) and not ok.connected and faults["stalls"] == 1 and faults["link_error"] == 1
    assert ok.connect() is not None  # the same device, opened again


def test_a_port_string_no_backend_takes_is_no_reason_to_retry():
    link = LinkSupervisor(settings("sim://?sede=2"), journal(), Counter(), open_device=open_device)
    with pytest.raises(PortError, match="sede"):
        link.connect()


def test_the_drift_watcher_keeps_its_monitor_only_for_the_calibration_it_was_watching():
    from magcal.sim.physics import demo_scenario

    cal = demo_scenario(2).physics.truth()
    j = journal()
    w = DriftWatcher(settings().daemon, j, Counter())
    assert w.wants_calibration
    w.adopt(cal, lambda a, b: a.close_to(b))
    monitor = w.monitor
    assert w.calibration is cal and not w.wants_calibration
    w.adopt(cal, lambda a, b: a.close_to(b))  # reconnected to the same record: the monitor goes on
    assert w.monitor is monitor
    w.adopt(None, lambda a, b: True)
    assert w.calibration is None and j.decisions() == [Decision.CALIBRATION_LOADED, Decision.NOTHING_STORED]


def test_the_recalibrator_solves_once_the_gates_pass_and_the_writer_verifies_by_read_back(tmp_path):
    s = settings(f"sim://?pace=0&seed=2&eeprom={tmp_path / 'e.bin'}", recalibrate=True)
    faults = Counter()
    j = journal()
    r = Recalibrator(s, j, faults)
    dev = open_device(s.port)
    dev.open()
    dev.start(100)
    session = None
    for items in batches(dev, 0.1):
        for item in items:
            r.take(item, collected=isinstance(item, Sample))
        session = r.poll(may_write=True, wanted=True)
        if session is not None:
            break
    assert session.result is not None and len(session.kept) >= READY_EVERY
    assert r.poll(may_write=True, wanted=True) is None  # a fresh session collects again
    w = CalibrationWriter(j, faults)
    stored = w.write(dev, session)
    assert stored is not None and dev.matches(stored, dev.read_calibration())
    assert w.count == 1 and w.last["verified"] is True
    assert j.decisions() == [Decision.SOLVING, Decision.WRITTEN]
    dev.close()


def test_the_state_keeper_saves_generations_and_refuses_a_state_of_another_kind(tmp_path):
    keeper = StateKeeper(tmp_path, journal(), Counter(), clock=lambda: 0.0)
    assert keeper.load() is None
    assert keeper.save(lambda g: {"kind": "something else", "generation": g}, every_s=5)
    assert keeper.generation == 1 and not keeper.due(4.9) and keeper.due(5.0)
    with pytest.raises(ValueError, match="state kind"):
        Saved.parse(keeper.load(), None)
    with StateDirLock(tmp_path), pytest.raises(StateError, match="another magcal daemon"):
        with StateDirLock(tmp_path):
            pass


def test_the_control_socket_answers_with_the_status(tmp_path):
    sock = ControlSocket(tmp_path, journal())
    sock.open()
    answer = {}
    asker = threading.Thread(target=lambda: answer.update(query_socket(tmp_path, timeout_s=5) or {}))
    asker.start()
    while asker.is_alive():
        sock.serve(lambda: {"running": True, "samples": 7})
        asker.join(0.01)
    sock.close()
    assert answer == {"running": True, "samples": 7}
    assert query_socket(tmp_path) is None  # closed: nobody answers, and the socket file is gone
