"""``magcal run`` with ``daemon.keep: tracker``: the device is kept calibrated by the tracker,
every write verified and charged to the EEPROM budget."""

import numpy as np
import pytest

from magcal.app.daemon import Collaborators, Daemon, Decision
from magcal.devices.simboard import SimEeprom
from magcal.recordings.state import StateFiles
from magcal.wire.protocol import record_from_calibration

from test_daemon import Tracked, make_settings

PAYLOAD = (30.5, -38.2, 14.8)


def _count_eeprom_writes(monkeypatch):
    """Every write the board makes to its EEPROM: a record, or the erase that discards one."""
    saved = []
    real = SimEeprom.put

    def put(self, offset, payload):
        saved.append(bytes(payload))
        return real(self, offset, payload)

    monkeypatch.setattr(SimEeprom, "put", put)
    return saved


def _codes(d):
    return [e["decision"] for e in d.journal.entries]


@pytest.mark.slow
def test_blank_board_then_a_payload_every_write_verified_and_within_budget(tmp_path, monkeypatch):
    saved = _count_eeprom_writes(monkeypatch)
    # the payload after the drift monitor has learnt its baseline (about 60 s in), so that both
    # the monitor's alarm and the tracker's restart are exercised
    t = Tracked("seed=7&fault=hard_iron@70=30.5,-38.2,14.8")
    d = t.run(tmp_path, 14000, recalibrate=True, write_burst=3)
    t.assert_exactly_once()
    k = d.tracking.keeper
    assert k.writes >= 2 and k.failed == 0  # the first one, and the payload's
    assert d.writer.count == k.writes and k.cycles == len(saved) == k.writes
    assert k.writes <= 3 + 14000 / 100 / 86400 * 24  # the burst, and what 140 s of budget refill
    np.testing.assert_allclose(d.drift.calibration.offset_ut, PAYLOAD, atol=0.6)
    status, values = t.board.eeprom.load_record()
    assert status == "OK" and values == record_from_calibration(d.drift.calibration)
    codes = _codes(d)
    assert Decision.KEEPING.value in codes and Decision.DRIFTED.value in codes
    # the alarm says the tracker starts afresh, not that a session collects (it is not the writer)
    after = codes[codes.index(Decision.DRIFTED.value):]
    assert Decision.TRACKER_RESTARTED.value in after and Decision.COLLECTING.value not in codes
    assert codes.count(Decision.WRITTEN.value) == k.writes
    st = d.status()["keeping"]
    assert st["writes"] == k.writes and st["eeprom_cycles"] == len(saved)


@pytest.mark.slow
def test_a_write_that_is_not_verified_is_charged_and_not_reported(tmp_path, monkeypatch):
    saved = _count_eeprom_writes(monkeypatch)
    t = Tracked("seed=7&fault=corrupt_write@0")
    d = t.run(tmp_path, 6000, recalibrate=True)
    k = d.tracking.keeper
    assert k.failed >= 1 and d.faults["verify_mismatch"] >= 1
    assert k.cycles == len(saved)  # the bad write and the restore both counted
    assert k.writes == d.writer.count  # only verified writes are reported
    if k.writes:
        status, values = t.board.eeprom.load_record()
        assert status == "OK" and values == record_from_calibration(d.drift.calibration)


@pytest.mark.slow
def test_no_write_without_recalibrate_and_the_keeper_resumes(tmp_path):
    t = Tracked("seed=12")
    d = t.run(tmp_path, 3000)  # recalibrate is off by default: nothing is written
    assert d.tracking.keeper.writes == 0 and t.board.eeprom.load_record()[0] == "BLANK"
    n = d.tracking.keeper.tracker.n
    assert n == d.intake.samples
    saved = StateFiles(tmp_path / "state").load()
    assert saved["resume"]["keeping"]["tracker"]["n"] == n
    again = Daemon(make_settings(t.url), state_dir=tmp_path / "state", max_samples=200,
                   collaborators=Collaborators(device_options=t.options(reply_timeout_s=0.25)))
    again.run()
    assert again.tracking.keeper.tracker.n > n  # it went on from what it remembered
