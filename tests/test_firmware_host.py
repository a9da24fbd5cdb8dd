"""The host's real serial client against the real firmware under the emulator (``emu://``).

Streaming without loss (also when the host stops reading for a while), a board reset seen as a
reset with no invented sample, and the whole calibrate → EEPROM → restart → read-back loop."""

from __future__ import annotations

import json
import time
from dataclasses import replace

import numpy as np
import pytest
from firmware_support import require_firmware

from magcal.cli import main as cli_main
from magcal.core.calibration import Calibration
from magcal.core.sample import Sample, counts_to_ut, temp_raw_to_c
from magcal.devices import Event, open_device
from magcal.sim.physics import HOFL_SUM_UT, Motion, demo_scenario
from magcal.wire.protocol import record_from_calibration


@pytest.fixture(autouse=True)
def _firmware():
    require_firmware()


def _samples(items):
    return [i for i in items if isinstance(i, Sample)]


def _events(items, kind):
    return [i for i in items if isinstance(i, Event) and i.kind == kind]


def _read_until(dev, n, items, timeout_s=60.0):
    """Read into ``items`` until it holds ``n`` samples (or the time is up)."""
    deadline = time.monotonic() + timeout_s
    while len(_samples(items)) < n and time.monotonic() < deadline:
        items.extend(dev.read(0.2))
    return items


def _is_subsequence(small, big) -> bool:
    it = iter(big)
    return all(any(x == y for y in it) for x in small)


def _until_held_back(board, quiet_s=0.3, limit_s=30.0) -> bool:
    """Wait, not reading, until the board has served no measurement for ``quiet_s``: the link's
    buffers are full and the board is held back (True), or ``limit_s`` has passed (False)."""
    served, since = len(board.served), time.monotonic()
    end = since + limit_s
    while time.monotonic() < end:
        time.sleep(0.05)
        if len(board.served) != served:
            served, since = len(board.served), time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return True
    return False


@pytest.mark.slow
def test_a_long_stream_loses_no_sample_when_the_host_stops_reading(tmp_path):
    """The host stops reading until the board is held back (the pty's buffers full: ~400 lines
    here) — as long as that takes on this machine, not a fixed 2 s — and then reads on: at
    least 1 500 consecutive samples, the backlog and 600 after it."""
    dev = open_device(f"emu://?seed=4&eeprom={tmp_path / 'ee.bin'}")
    with dev:
        ident = dev.open()
        assert (ident.who_am_i, ident.wia) == (0x68, 0x48)
        dev.start(100)
        items, held, want = [], None, 1500
        deadline = time.monotonic() + 90
        while len(_samples(items)) < want and time.monotonic() < deadline:
            items.extend(dev.read(0.2))
            if held is None and len(_samples(items)) >= 500:
                held = _until_held_back(dev.board)  # the board must wait for the host, not drop lines
                want = max(want, len(dev.board.served) + 600)  # the backlog, then 600 more
        dev.stop()
        items.extend(dev.read(0.3))
        stats = dev.stats()
    samples = _samples(items)
    assert held, "the board went on serving measurements while the host did not read"
    assert len(samples) >= want, f"only {len(samples)} samples in 90 s"
    assert not _events(items, "gap") and not _events(items, "reset"), stats
    seqs = [s.seq for s in samples]
    assert all(b - a == 1 for a, b in zip(seqs, seqs[1:])), "samples are consecutive lines"
    # every sample is a measurement the physics served, in order, and none is missing
    served = [r for (_, _, r, _, _) in dev.board.served]
    got = [s.raw for s in samples]
    assert got == served[: len(got)], "samples differ from the measurements served"
    t = np.array([s.t_s for s in samples])
    assert np.all(np.diff(t) > 0)
    assert abs(np.median(np.diff(t)) - 0.010) < 0.0015


def test_reset_mid_stream_is_seen_as_a_reset_and_no_sample_is_invented(tmp_path):
    dev = open_device(f"emu://?seed=6&eeprom={tmp_path / 'ee.bin'}")
    with dev:
        dev.open()
        dev.start(100)
        items = []
        while len(_samples(items)) < 200:
            items.extend(dev.read(0.2))
        dev.board.reset()
        end = time.monotonic() + 3
        while not _events(items, "reset") and time.monotonic() < end:
            items.extend(dev.read(0.2))
        resets = _events(items, "reset")
        assert len(resets) == 1, items[-5:]
        # after its reset the board is idle until told to stream again
        quiet = _samples(dev.read(0.5))
        assert quiet == []
        dev.start(100)
        after = []
        while len(_samples(after)) < 100:
            after.extend(dev.read(0.2))
        dev.stop()
    samples = _samples(items) + _samples(after)
    # the measurement in flight at the reset leaves DRDY set in the sensor (which the AVR reset
    # does not touch): the firmware must clear it, not read it mid-conversion (DERR)
    assert not [s for s in samples if s.st2 & 0x04], "a sample was read during a conversion"
    got = [s.raw for s in samples]
    served = [r for (_, _, r, _, _) in dev.board.served]
    assert _is_subsequence(got, served), "a sample that the sensor never measured appeared"
    # lost: what the reset cut off (the measurement in flight and up to two lines still in the
    # 64-byte UART buffer, as on a real board) and the measurement in flight at the final stop
    assert len(served) - len(got) <= 5, (len(served), len(got))
    t = [s.t_s for s in samples]
    assert all(b > a for a, b in zip(t, t[1:])), "host time keeps increasing across the reset"


@pytest.mark.slow
def test_calibrate_write_restart_read_back_and_calibrated_stream(tmp_path, capsys):
    ee = tmp_path / "ee.bin"
    url = f"emu://?seed=1&eeprom={ee}"
    # at 20 Hz: the same turning in ~750 samples instead of ~1 750 (less than half the work for
    # the emulated AVR, the physics and the host); what is checked here is the loop through the
    # EEPROM and the board's own correction, which does not depend on the rate
    code = cli_main(["calibrate", "--port", url, "--rate", "20", "--json", "--timeout", "120"])
    out = capsys.readouterr().out
    report = json.loads(out[out.index("{"):])
    assert code == 0, report.get("message")
    assert report["written"] and report["verified"]
    written = Calibration.from_dict(report["calibration"])
    assert ee.exists() and ee.stat().st_size == 1024

    # a new harness process on the same EEPROM file: a restarted board
    dev = open_device(url)
    with dev:
        dev.open()
        stored = dev.read_calibration()
        assert stored is not None
        assert record_from_calibration(stored) == record_from_calibration(written)
        truth = dev.board.scenario.physics
        dev.set_output(True)
        dev.start(50)
        items = []
        while len(_samples(items)) < 300:
            items.extend(dev.read(0.2))
        dev.stop()
    cal = np.array([s.field_ut for s in _samples(items)])
    assert all(s.aux.get("calibrated") for s in _samples(items))
    # the board's float32 correction equals the host's float64 one for the same measurements
    served = list(dev.board.served)[: len(cal)]
    m = counts_to_ut([r for (_, _, r, _, _) in served], truth.asa)
    temp_c = np.array([temp_raw_to_c(t) for (_, _, _, _, t) in served])
    want = stored.correct(m, {"temp_c": temp_c})
    np.testing.assert_allclose(cal, want, atol=0.005)
    norms = np.linalg.norm(cal, axis=1)
    # centred: every calibrated sample sits on the sphere of the Earth field around the origin
    assert abs(np.median(norms) - truth.field_ut) < 0.6, np.median(norms)
    assert np.percentile(np.abs(norms - truth.field_ut), 95) < 1.5
    np.testing.assert_allclose(stored.offset_ut, truth.hard_iron_ut, atol=0.5)


@pytest.mark.slow
def test_overflow_is_flagged_in_st2_exactly_when_the_sensor_overflowed(tmp_path):
    # a still board whose |x|+|y|+|z| sits on the AK8975's 2400 µT overflow limit: noise decides
    still = replace(demo_scenario(2), motion=Motion("still"))
    sc = still.with_physics(hard_iron_ut=(800.0, 800.0, 800.0))
    m, _ = sc.field_ut([0.0], [0])
    sc = sc.with_physics(hard_iron_ut=(800.0 - (float(np.abs(m[0]).sum()) - HOFL_SUM_UT), 800.0, 800.0))
    dev = open_device(f"emu://?eeprom={tmp_path / 'ee.bin'}", scenario=sc)
    with dev:
        dev.open()
        dev.start(100)
        items = _read_until(dev, 400, [])
        dev.stop()
    samples = _samples(items)
    served = list(dev.board.served)[: len(samples)]
    assert [s.raw for s in samples] == [r for (_, _, r, _, _) in served]
    st2 = [s.st2 for s in samples]
    assert st2 == [s for (_, _, _, s, _) in served]
    assert 0 < st2.count(0x08) < len(st2), "the scenario should straddle the overflow limit"
    assert all(not s.valid for s in samples if s.st2 & 0x08)


@pytest.mark.slow
def test_a_magnetometer_that_never_finishes_is_logged_and_the_board_stays_responsive(tmp_path):
    dev = open_device(f"emu://?fault=stuck_drdy&eeprom={tmp_path / 'ee.bin'}")
    with dev:
        dev.open()
        dev.start(50)
        items = dev.read(1.0) + dev.read(0.5)
        assert _samples(items) == []
        assert dev.read_record().status == "BLANK"  # commands still answered
        dev.stop()
        assert dev.counters["log_lines"] >= 3  # one "DRDY timeout" line per attempt


def test_through_the_host_client_bad_commands_are_refused_and_streaming_goes_on(tmp_path):
    from magcal.core.errors import DeviceError

    dev = open_device(f"emu://?seed=3&eeprom={tmp_path / 'ee.bin'}")
    with dev:
        dev.open()
        dev.start(100)
        dev.read(0.3)
        dev.transport.write(b"$G,9*00\n~~~ line noise ~~~\n$Q\n")  # bad CRC, noise, no CRC
        with pytest.raises(DeviceError, match="UNKNOWN"):
            dev.command("Q")
        with pytest.raises(DeviceError, match="RANGE"):
            dev.command("R", 0)
        with pytest.raises(DeviceError, match="RANGE"):
            dev.command("F", 10)
        items = []
        while len(_samples(items)) < 100:
            items.extend(dev.read(0.2))
        dev.stop()
        assert dev.framer.counters["lost_lines"] == 0
    assert not _events(items, "gap") and not _events(items, "reset")


@pytest.mark.parametrize("addr", ["0x68", "0x69"])
def test_the_firmware_finds_the_mpu_with_ad0_low_or_high(tmp_path, addr):
    """Breakouts differ in how they tie AD0; the firmware looks at both addresses, so the same
    sketch identifies and streams from either."""
    dev = open_device(f"emu://?seed=5&addr={addr}&eeprom={tmp_path / 'ee.bin'}")
    with dev:
        ident = dev.open()
        assert (ident.who_am_i, ident.wia) == (0x68, 0x48)
        dev.start(100)
        items = _read_until(dev, 50, [], timeout_s=30)
        dev.stop()
    samples = _samples(items)
    assert len(samples) >= 50 and all(s.valid for s in samples)
    served = [r for (_, _, r, _, _) in dev.board.served]
    assert [s.raw for s in samples] == served[: len(samples)]


def test_an_emulated_board_at_an_impossible_address_is_refused_plainly():
    from magcal.core.errors import PortError

    with pytest.raises(PortError, match="0x68 .AD0 low. or 0x69"):
        open_device("emu://?addr=0x70")


@pytest.mark.slow
def test_the_firmware_self_test_reads_the_coil_and_streaming_goes_on(tmp_path):
    """``T`` on the real sketch: the coil's registers as the chip holds them, judged with the
    board's ASA; a dead coil fails on z alone; a self-test in the middle of a stream loses and
    invents no sample."""
    healthy = demo_scenario(7)
    dev = open_device(f"emu://?eeprom={tmp_path / 'ee.bin'}", scenario=healthy)
    with dev:
        dev.open()
        dev.start(100)
        items = _read_until(dev, 100, [])
        result = dev.self_test()
        _read_until(dev, 250, items)
        dev.stop()
        items.extend(dev.read(0.3))
    assert result.passed and result.raw == healthy.physics.self_test_raw()
    samples = _samples(items)
    assert not _events(items, "gap")
    served = [r for (_, _, r, _, _) in dev.board.served]
    assert [s.raw for s in samples] == served[: len(samples)], "a sample was lost or invented around the self-test"

    dead = demo_scenario(7).with_physics(self_test_counts=(12, -18, -4))  # the coil gives nothing on z
    dev = open_device(f"emu://?eeprom={tmp_path / 'ee2.bin'}", scenario=dead)
    with dev:
        dev.open()
        result = dev.self_test()
    assert result.axis_passed == (True, True, False) and not result.passed
