"""The MotionCal dialect over a real pty, against a simulated Adafruit calibration sketch."""

from __future__ import annotations

import time

import numpy as np
import pytest
from adafruit_device import AdafruitBoard

from magcal.core.calibration import Calibration
from magcal.core.errors import NoReply, WriteRejected
from magcal.devices import open_device
from magcal.devices.motioncal_client import MotionCalDevice
from magcal.wire import motioncal as mc

FAST = dict(echo_timeout_s=1.0, tries=2, open_timeout_s=3.0)


def collect(dev, n: int, limit_s: float = 20.0):
    out = []
    deadline = time.monotonic() + limit_s
    while len(out) < n and time.monotonic() < deadline:
        out += dev.read(0.05)
    return out


def first_index(sent: np.ndarray, value, atol: float) -> int:
    hit = np.flatnonzero(np.all(np.abs(sent - value) <= atol, axis=1))
    assert len(hit), "a sample that the board never sent"
    return int(hit[0])


def match_in_order(got: np.ndarray, sent: np.ndarray, atol: float) -> list[int] | None:
    """Indices into ``sent`` of each of ``got`` matched in order, or None if one is not there."""
    idx, j = [], 0
    for g in got:
        while j < len(sent) and not np.all(np.abs(sent[j] - g) <= atol):
            j += 1
        if j == len(sent):
            return None
        idx.append(j)
        j += 1
    return idx


def target_calibration(board: AdafruitBoard) -> Calibration:
    truth = board.scenario.physics.truth()
    return Calibration(offset_ut=truth.offset_ut, field_ut=truth.field_ut, soft_iron=truth.soft_iron)


@pytest.mark.parametrize("ending", ["\r", "\n", "\r\n"])
def test_raw_lines_with_any_ending_arrive_as_samples(ending):
    with AdafruitBoard(ending=ending, uni=False) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            ident = dev.open()
            assert ident.transport == "motioncal" and ident.asa == (128, 128, 128) and ident.firmware == ""
            got = collect(dev, 300)
            sent = np.round(np.array(board.sent_field_ut) * 10) / 10
    f = np.array([s.field_ut for s in got])
    assert len(got) >= 300
    assert [s.seq for s in got] == list(range(len(got)))  # counted by the host
    assert all(s.raw is None for s in got)
    assert np.all(np.diff([s.t_s for s in got]) >= 0)
    # lossless on a clean link: a contiguous run of the readings the board made (pyserial
    # flushes what was waiting when it opened the port, as a real board's reset would)
    j = first_index(sent, f[0], atol=1e-9)
    assert np.allclose(f, sent[j : j + len(f)], atol=1e-9)
    assert dev.counters["malformed"] == 0 and dev.counters["cal1"] >= 2


def test_uni_lines_give_the_finer_reading_once():
    with AdafruitBoard(uni=True) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            got = collect(dev, 300)
            sent = np.array(board.sent_field_ut)
    f = np.array([s.field_ut for s in got])
    # one sample per reading (never a Raw: and its Uni: twin), at 0.01 µT after the first
    # (the first line seen after opening may be a Raw: or, when its Raw: was flushed, a Uni:)
    j = first_index(np.round(sent, 2), f[1], atol=1e-9) - 1
    assert np.allclose(f[0], sent[j], atol=0.05 + 1e-9)
    assert np.allclose(f[1:], np.round(sent[j + 1 : j + len(f)], 2), atol=1e-9)


def test_noise_and_torn_lines_are_counted_never_merged():
    with AdafruitBoard(noise=0.08, torn=0.08, seed=5) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            got = collect(dev, 1500)
            sent = np.array(board.sent_field_ut)
    f = np.array([s.field_ut for s in got])
    assert len(f) >= 1500
    assert dev.counters["malformed"] > 50 and dev.counters["junk"] > dev.counters["malformed"]
    # every sample is a reading the board really made, in order (0.1 µT Raw or 0.01 µT Uni)
    idx = match_in_order(f, sent, atol=0.05 + 1e-9)
    assert idx is not None
    # and most readings made meanwhile arrive (a torn or noisy line costs its reading)
    assert len(f) > 0.75 * (idx[-1] - idx[0] + 1)


def test_write_is_verified_by_the_echo_and_the_device_applies_it_right():
    with AdafruitBoard(cal_period=60) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            collect(dev, 200)
            want = dev.prepare(target_calibration(board))
            echoed = dev.write_calibration(want)
            assert dev.matches(want, echoed)
            assert dev.read_calibration() is echoed
            assert dev.counters["echo_verified"] == 1
        stored = (board.mag_hardiron, board.mag_softiron, board.packets_stored, board.crc_failures)
    hard, soft, n_stored, crc_bad = stored
    assert n_stored == 1 and crc_bad == 0
    # the board's own arithmetic (hard iron, then its 3×3 from the packet) inverts the forward model
    rng = np.random.default_rng(1)
    h = rng.normal(size=(100, 3))
    h *= 48.0 / np.linalg.norm(h, axis=1, keepdims=True)
    m = want.distort(h)
    corrected = (m - np.array(hard)) @ np.array(soft).reshape(3, 3).T
    assert np.abs(corrected - h).max() < 1e-3


def test_an_echo_printed_before_the_store_does_not_fail_the_write():
    """Cal1/Cal2 lines already on their way when the packet goes out show the old values."""
    with AdafruitBoard(cal_period=20, store_delay_loops=15) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            collect(dev, 100)
            want = dev.prepare(target_calibration(board))
            assert dev.matches(want, dev.write_calibration(want))
            assert dev.counters["packets_sent"] == 1 and board.packets_stored == 1


def test_old_echoes_waiting_in_the_port_buffer_do_not_fail_the_write():
    """While the host fits, the board keeps printing; the backlog holds many old Cal lines."""
    with AdafruitBoard(cal_period=10) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            collect(dev, 100)
            time.sleep(0.4)  # not reading: the OS buffers a backlog of old Raw/Cal lines
            want = dev.prepare(target_calibration(board))
            assert dev.matches(want, dev.write_calibration(want))
            assert dev.counters["packets_sent"] == 1 and board.packets_stored == 1


def test_read_calibration_waits_for_the_next_echo_after_open():
    with AdafruitBoard(cal_period=100) as board:
        board.mag_hardiron = [12.5, -3.25, 40.0]
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            cal = dev.read_calibration()  # nothing seen yet: listens for one Cal1/Cal2 cycle
            assert cal is not None and np.allclose(cal.offset_ut, [12.5, -3.25, 40.0])
            assert len(dev.read(0.0)) > 0  # the readings that arrived meanwhile are kept


@pytest.mark.slow
def test_device_that_never_echoes_gets_a_plain_no_reply():
    with AdafruitBoard(echo="never") as board:
        with open_device(board.port, dialect="motioncal", echo_timeout_s=0.6, tries=3) as dev:
            dev.open()
            with pytest.raises(NoReply) as err:
                dev.write_calibration(target_calibration(board))
            assert dev.counters["packets_sent"] == 3
            assert dev.read_calibration() is None
    msg = str(err.value)
    assert "no Cal1/Cal2 echo within 1.8 s after 3 tries" in msg
    assert "no calibration packet handler" in msg and "does not print them at all" in msg


@pytest.mark.parametrize("mode", ["wrong", "ignore"])
def test_device_that_echoes_other_values_is_rejected(mode):
    with AdafruitBoard(echo=mode, cal_period=40) as board:
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            want = target_calibration(board)
            with pytest.raises(WriteRejected, match="hard_iron_x") as err:
                dev.write_calibration(want)
            assert dev.counters["packets_sent"] == 2
            assert not dev.matches(want, dev.read_calibration())
    if mode == "wrong":  # it did store the packet: the CRC was fine, its echo was not
        assert board.packets_stored == 2 and board.crc_failures == 0
        assert "before" not in str(err.value)
    else:  # prints Cal lines, never takes the packet: the echo is the old calibration
        assert board.packets_stored == 0
        assert "probably has no packet handler" in str(err.value)
    assert "echo" in str(err.value)


def test_accel_and_gyro_offsets_already_on_the_device_are_kept():
    with AdafruitBoard(cal_period=40) as board:
        board.accel_zerog = [0.25, -0.125, 0.5]
        board.gyro_zerorate = [0.015, 0.0, -0.02]
        with open_device(board.port, dialect="motioncal", **FAST) as dev:
            dev.open()
            collect(dev, 200)  # long enough to see a Cal1 line
            dev.write_calibration(target_calibration(board))
        acc, gyr = board.accel_zerog, board.gyro_zerorate
    assert np.allclose(acc, [0.25, -0.125, 0.5]) and np.allclose(gyr, [0.015, 0.0, -0.02], atol=1e-6)


def test_prepare_drops_terms_the_packet_cannot_carry():
    dev = MotionCalDevice("loop://")
    cal = Calibration(offset_ut=[1.0, 2.0, 3.0], field_ut=50.0, coef_ut_per_unit={"temp_c": [0.1, 0.0, 0.0]})
    p = dev.prepare(cal)
    assert p.coef_ut_per_unit == {} and dev.counters["terms_dropped"] == 1
    assert np.allclose(p.offset_ut, np.float32([1.0, 2.0, 3.0]))


def test_silent_port_is_reported_at_open():
    with AdafruitBoard(echo="never") as board:
        board._stop.set()  # the sketch is not running: nothing on the line
        board._thread.join()
        dev = open_device(board.port, dialect="motioncal", open_timeout_s=0.3)
        with pytest.raises(NoReply, match="no Raw: or Uni: line within 0.3 s at 115200 baud"):
            dev.open()


def test_auto_dialect_finds_a_motioncal_board():
    with AdafruitBoard() as board:
        dev = open_device(board.port, dialect="auto", **FAST)
        try:
            assert isinstance(dev, MotionCalDevice)
            dev.open()
            assert len(collect(dev, 50)) >= 50
        finally:
            dev.close()


def test_compare_tolerance_accepts_a_printed_echo_only():
    tol = MotionCalDevice.compare_tolerance
    a = Calibration(offset_ut=[10.0, 0.0004, -3.0], field_ut=48.0)
    assert a.close_to(Calibration(offset_ut=[10.0, 0.0, -3.0], field_ut=48.0), **tol)
    assert not a.close_to(Calibration(offset_ut=[10.01, 0.0, -3.0], field_ut=48.0), **tol)
    assert mc.compare_tolerance()["atol_w"] < 1e-3


def test_unplugged_board_is_port_unavailable():
    from magcal.core.errors import PortUnavailable

    board = AdafruitBoard().start()
    with open_device(board.port, dialect="motioncal", **FAST) as dev:
        dev.open()
        board.stop()  # the other end of the pty goes away, as a USB unplug does
        with pytest.raises(PortUnavailable):
            for _ in range(50):
                dev.read(0.05)
