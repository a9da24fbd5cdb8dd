"""The v1 protocol client against the sim:// board (the same client serves serial ports)."""

import numpy as np
import pytest

from magcal.core.calibration import Calibration
from magcal.core.errors import DeviceError, NoReply
from magcal.core.events import Event
from magcal.core.sample import Sample
from magcal.devices import open_device


def collect(dev, n):
    items = []
    while sum(isinstance(i, Sample) for i in items) < n:
        items += dev.read(0.2)
    return items


def test_identify_reports_chip_and_asa():
    with open_device("sim://?pace=0&seed=4") as dev:
        ident = dev.open()
        assert ident.who_am_i == 0x68 and ident.wia == 0x48
        assert ident.asa == (176, 178, 166) and ident.proto == 1


def test_stream_has_consecutive_sequence_numbers_and_asa_adjusted_field():
    with open_device("sim://?pace=0&seed=4") as dev:
        dev.open()
        dev.start(100)
        items = collect(dev, 2000)
        samples = [i for i in items if isinstance(i, Sample)]
        seqs = np.array([s.seq for s in samples])
        assert np.all(np.diff(seqs) % 65536 == 1)
        assert not [i for i in items if isinstance(i, Event)]
        s = samples[0]
        assert s.field_ut[0] == pytest.approx(s.raw[0] * 0.3 * (176 + 128) / 256)
        t = np.array([s.t_s for s in samples])
        assert np.allclose(np.diff(t), 0.01)


def test_identity_reports_the_rate_the_device_was_set_to():
    with open_device("sim://?pace=0") as dev:
        assert dev.open().rate_hz == 100
        dev.start(25)
        assert dev.identity.rate_hz == 25


def test_unsolicited_reset_is_reported_and_no_sample_is_invented():
    with open_device("sim://?pace=0&seed=4") as dev:
        dev.open()
        dev.start(100)
        before = [i for i in collect(dev, 100) if isinstance(i, Sample)]
        dev.board.power_cycle()
        after = dev.read(0.2)
        events = [i for i in after if isinstance(i, Event)]
        assert [e.kind for e in events] == ["reset"]
        assert not [i for i in after if isinstance(i, Sample) and i.seq > before[-1].seq + 5]
        assert dev.stats()["device_resets"] == 1
        # after a reset the board is idle until told to stream again
        dev.start(100)
        again = [i for i in collect(dev, 10) if isinstance(i, Sample)]
        assert again[0].t_s > before[-1].t_s  # host time stays monotonic across the reset


def test_requested_reset_is_not_a_fault():
    with open_device("sim://?pace=0&seed=4") as dev:
        dev.open()
        ident = dev.reset()
        assert ident.wia == 0x48
        assert not [i for i in dev.read(0.1) if isinstance(i, Event)]
        assert dev.stats().get("device_resets", 0) == 0


def test_calibration_survives_a_restart_on_the_same_eeprom_file(tmp_path):
    eeprom = tmp_path / "eeprom.bin"
    cal = Calibration([23.5, -41.2, 12.8], 49.9, soft_iron=[[1.01, 0.001, 0], [0.001, 0.99, 0], [0, 0, 1]])
    with open_device(f"sim://?pace=0&eeprom={eeprom}") as dev:
        dev.open()
        assert dev.read_calibration() is None and dev.record_status == "BLANK"
        echoed = dev.write_calibration(dev.prepare(cal))
        assert dev.matches(dev.prepare(cal), echoed)
    with open_device(f"sim://?pace=0&eeprom={eeprom}") as dev:
        dev.open()
        back = dev.read_calibration()
        assert dev.matches(dev.prepare(cal), back)


def test_corrupt_eeprom_is_reported_never_applied(tmp_path):
    eeprom = tmp_path / "eeprom.bin"
    with open_device(f"sim://?pace=0&eeprom={eeprom}") as dev:
        dev.open()
        dev.write_calibration(Calibration([1, 2, 3], 50))
    blob = bytearray(eeprom.read_bytes())
    blob[5] ^= 0x40
    eeprom.write_bytes(bytes(blob))
    with open_device(f"sim://?pace=0&eeprom={eeprom}") as dev:
        dev.open()
        assert dev.read_calibration() is None
        assert dev.record_status == "CORRUPT"
        with pytest.raises(DeviceError, match="RANGE"):
            dev.set_output(True)


def test_calibrated_output_applies_the_stored_record():
    with open_device("sim://?pace=0&seed=2") as dev:
        dev.open()
        truth = dev.board.scenario.physics.truth()
        dev.write_calibration(Calibration(truth.offset_ut, truth.field_ut, truth.soft_iron))
        dev.set_output(True)
        dev.start(100)
        samples = [i for i in collect(dev, 500) if isinstance(i, Sample)]
        h = np.array([s.field_ut for s in samples])
        assert all(s.aux.get("calibrated") for s in samples)
        assert abs(np.linalg.norm(h, axis=1).mean() - truth.field_ut) < 0.3
        assert np.linalg.norm(h, axis=1).std() < 1.0  # a sphere about the origin: no hard iron left


def test_a_mute_device_is_a_clear_no_reply():
    dev = open_device("sim://?pace=0")
    dev.board.faults["mute"] = True
    dev.boot_timeout_s = 0.5
    dev.board._out.clear()
    with pytest.raises(NoReply, match="did not identify"):
        dev.open()


def test_refused_write_raises_write_rejected():
    with open_device("sim://?pace=0") as dev:
        dev.open()
        with pytest.raises(DeviceError, match="RECCRC"):
            dev.command("W", 1, 0, 0, 0, 50000, 10**6, 10**6, 10**6, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, "0000")



def test_malformed_and_unknown_commands_get_error_replies():
    with open_device("sim://?pace=0") as dev:
        dev.open()
        with pytest.raises(DeviceError, match="UNKNOWN"):
            dev.command("Q")
        with pytest.raises(DeviceError, match="RANGE"):
            dev.command("R", 500)
        dev.transport.write(b"$G,1*00\n")  # bad checksum: an E line with tag 0
        dev.start(50)
        assert [i for i in collect(dev, 10) if isinstance(i, Sample)]
