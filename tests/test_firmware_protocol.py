"""The real firmware under simavr, spoken to with raw pyserial on the harness's pty.

Protocol-level behaviour a host relies on: identity at boot, error replies that never stop the
stream, record validation, the EEPROM layout of docs/protocol.md, rate and reset commands."""

from __future__ import annotations

import re
import struct
import time

import numpy as np
import pytest
from firmware_support import RawBoard, make_size_output, require_firmware

from magcal.wire.protocol import (
    Ack,
    ErrorReply,
    Hello,
    RawSample,
    RecordReply,
    crc8,
    encode_command,
    record_crc,
)


@pytest.fixture(autouse=True)
def _firmware():
    require_firmware()


@pytest.fixture
def board(tmp_path):
    b = RawBoard(tmp_path)
    yield b
    b.close()


def _boot(b: RawBoard) -> Hello:
    return b.wait_for(lambda i: isinstance(i, Hello), 5, "boot hello")


def _reply(b: RawBoard, tag: int):
    return b.wait_for(lambda i: isinstance(i, (Ack, ErrorReply, RecordReply)) and i.tag == tag,
                      5, f"reply to tag {tag}")


def test_build_fits_the_uno_with_ram_headroom():
    out = make_size_output()
    flash = int(re.search(r"flash: (\d+)", out).group(1))
    ram = int(re.search(r"ram: (\d+)", out).group(1))
    assert flash < 32256, out
    # 2 KiB of SRAM: data + bss must leave room for the stack
    assert ram < 1200, f"static RAM {ram} bytes leaves too little stack: {out}"


def test_boot_hello_reports_identity_and_fuse_rom(tmp_path):
    b = RawBoard(tmp_path, extra=("--asa", "130,141,152"))
    try:
        h = _boot(b)
        assert h.seq == 0 and h.proto == 1
        assert (h.who_am_i, h.wia) == (0x68, 0x48)
        assert h.asa == (130, 141, 152)
        tag = b.send("I")
        assert isinstance(_reply(b, tag), Ack)
        again = b.wait_for(lambda i: isinstance(i, Hello), 5, "hello after I")
        assert again.seq > 0, "I must not restart the sequence numbers"
    finally:
        b.close()


def test_missing_magnetometer_is_reported_in_the_hello(tmp_path):
    b = RawBoard(tmp_path, extra=("--faults", "2"))  # MPU_FAULT_NO_AK
    try:
        h = _boot(b)
        assert h.who_am_i == 0x68
        assert h.wia == 0 and h.asa == (0, 0, 0)
    finally:
        b.close()


@pytest.mark.slow
def test_bad_lines_get_error_replies_and_the_stream_goes_on(board):
    _boot(board)
    board.send("R", 100)
    tag = board.send("G")
    _reply(board, tag)
    board.pump(0.3)
    payload = b"R,40,5"
    bad = [
        (b"$" + payload + b"*%02X\n" % (crc8(payload) ^ 0x55), "CRC"),       # wrong checksum
        (encode_command("Q", 41), "UNKNOWN"),                                  # unknown letter
        (encode_command("R", 42, 5, 6), "SYNTAX"),                             # field count
        (encode_command("R", 43, "x5"), "SYNTAX"),                             # not a number
        (b"$" + b"R,44," + b"1" * 150 + b"*00\n", "LONG"),                     # over-long
        (b"no dollar here\n$G,45\n", "SYNTAX"),                                # noise, no CRC
        (encode_command("R", 46, 500), "RANGE"),
    ]
    for line, code in bad:
        before = len(board.items)
        board.write(line)
        err = board.wait_for(lambda i: isinstance(i, ErrorReply), 5, f"error {code}")
        assert err.code == code, (line, err)
        after = board.pump(0.15)
        assert sum(isinstance(i, RawSample) for i in after) >= 5, f"stream stalled after {code}"
        assert len(board.items) > before
    unknown = [i for i in board.items if isinstance(i, ErrorReply) and i.code == "UNKNOWN"]
    assert unknown[0].tag == 41 and unknown[0].cmd == "?"
    assert board.framer.counters["lost_lines"] == 0
    assert board.framer.counters["bad_checksums"] == 0


def test_rate_command_sets_the_measurement_period(board):
    _boot(board)
    tag = board.send("R", 20)
    ack = _reply(board, tag)
    assert isinstance(ack, Ack) and ack.result == ("20",)
    board.send("G")
    items = board.pump(1.5)
    ms = [i.ms for i in items if isinstance(i, RawSample)]
    assert len(ms) >= 5
    steps = [b - a for a, b in zip(ms[1:], ms[2:])]
    assert all(48 <= s <= 52 for s in steps), steps
    for bad in (0, 101):
        err = _reply(board, board.send("R", bad))
        assert isinstance(err, ErrorReply) and err.code == "RANGE"


def test_samples_carry_the_sensor_registers(board):
    _boot(board)
    board.send("G")
    s = board.wait_for(lambda i: isinstance(i, RawSample), 5, "sample")
    assert s.raw == (100, -200, 300)
    assert s.st2 == 0 and s.temp_raw == -2150
    assert s.accel == (0, 0, 16384)  # ACCEL_XOUT_H..ZOUT_L as read: the harness's board lies flat, +1 g on z


def _record(offset_nt=(23500, -41200, 12800)):
    return (1, *offset_nt, 50000, 1000000, 990000, 1010000, 1000, -2000, 3000,
            10, -20, 30, 2700, 0, 0, 0)


def test_record_is_validated_before_it_is_stored(board):
    _boot(board)
    k = _reply(board, board.send("K"))
    assert k.status == "BLANK" and not any(k.values)
    err = _reply(board, board.send("M", 1))
    assert isinstance(err, ErrorReply) and err.code == "RANGE", "blank record must never be applied"

    vals = _record()
    crc = record_crc(vals)
    err = _reply(board, board.send("W", *vals, f"{crc ^ 1:04X}"))
    assert isinstance(err, ErrorReply) and err.code == "RECCRC"
    v2 = (2, *vals[1:])
    err = _reply(board, board.send("W", *v2, f"{record_crc(v2):04X}"))
    assert isinstance(err, ErrorReply) and err.code == "RANGE"
    assert _reply(board, board.send("K")).status == "BLANK"

    tag = board.send("W", *vals, f"{crc:04X}")
    assert isinstance(_reply(board, tag), Ack)
    rec = board.wait_for(lambda i: isinstance(i, RecordReply) and i.tag == tag, 5, "C after W")
    assert rec.status == "OK" and rec.values == vals and rec.crc == crc
    ack = _reply(board, board.send("M", 1))
    assert isinstance(ack, Ack)


def _eeprom_blob(vals) -> bytes:
    blob = bytes([0x4D]) + struct.pack("<18i", *vals) + struct.pack("<H", record_crc(vals))
    return blob + b"\xff" * (1024 - len(blob))


def test_eeprom_layout_matches_the_protocol_document(tmp_path):
    ee = tmp_path / "ee.bin"
    vals = _record((1, -2, 3))
    ee.write_bytes(_eeprom_blob(vals))
    b = RawBoard(tmp_path, eeprom=ee)
    try:
        _boot(b)
        rec = _reply(b, b.send("K"))
        assert rec.status == "OK" and rec.values == vals
    finally:
        b.close()


@pytest.mark.parametrize("flip", [0, 5, 40, 74])  # magic, a value byte, another, the CRC
def test_corrupt_eeprom_is_reported_and_never_applied(tmp_path, flip):
    ee = tmp_path / "ee.bin"
    blob = bytearray(_eeprom_blob(_record()))
    blob[flip] ^= 0x10
    ee.write_bytes(bytes(blob))
    b = RawBoard(tmp_path, eeprom=ee)
    try:
        _boot(b)
        rec = _reply(b, b.send("K"))
        assert rec.status == "CORRUPT" and not any(rec.values)
        err = _reply(b, b.send("M", 1))
        assert isinstance(err, ErrorReply) and err.code == "RANGE"
        b.send("G")
        s = b.wait_for(lambda i: isinstance(i, RawSample), 5, "raw sample")
        assert s.raw == (100, -200, 300)
    finally:
        b.close()


def test_calibrated_output_applies_the_stored_record(tmp_path):
    """U lines = W (m − o − t (T − tref)) as the host computes it, from the stored record."""
    from magcal.core.sample import counts_to_ut, temp_raw_to_c
    from magcal.wire.protocol import CalibratedSample, calibration_from_record

    vals = (1, 10000, -20000, 30000, 50000, 1020000, 980000, 1005000, 12000, -8000, 5000,
            150, -300, 220, 2500, 0, 0, 0)
    ee = tmp_path / "ee.bin"
    ee.write_bytes(_eeprom_blob(vals))
    b = RawBoard(tmp_path, eeprom=ee)
    try:
        _boot(b)
        assert isinstance(_reply(b, b.send("M", 1)), Ack)
        b.send("G")
        u = b.wait_for(lambda i: isinstance(i, CalibratedSample), 5, "calibrated sample")
    finally:
        b.close()
    m = counts_to_ut([(100, -200, 300)], (176, 178, 166))
    want = calibration_from_record(vals).correct(m, {"temp_c": [temp_raw_to_c(-2150)]})[0] * 1000
    assert np.allclose(u.field_nt, want, atol=2), (u.field_nt, want)
    assert u.temp_raw == -2150


def test_software_reset_restarts_the_sequence(board):
    _boot(board)
    board.send("G")
    board.pump(0.2)
    tag = board.send("Z")
    _reply(board, tag)
    h = board.wait_for(lambda i: isinstance(i, Hello), 5, "hello after Z")
    assert h.seq == 0
    more = board.pump(0.3)
    assert not any(isinstance(i, RawSample) for i in more), "a reset stops streaming"


def test_reopening_the_port_restarts_the_board_like_an_uno(board):
    """Opening the port of an Uno pulses DTR and resets it: the emulated board does the same
    when a host opens its pty after it had been closed (the harness sees the close)."""
    _boot(board)
    board.send("G")
    board.pump(0.3)
    board.port.close()
    time.sleep(0.2)
    board.port.open()
    h = board.wait_for(lambda i: isinstance(i, Hello), 5, "hello after reopening")
    assert h.seq == 0
    assert board.framer.counters["restarts"] >= 1


def test_a_line_of_exactly_120_bytes_is_accepted_and_121_is_too_long(board):
    _boot(board)
    vals = list(_record())
    widths = [int("5" * d) * sign for d in range(1, 10) for sign in (1, -1)]
    for ix in widths:  # find a record whose W line is exactly 120 bytes
        for iy in widths:
            vals[14], vals[15], vals[16] = 555555555, ix, iy
            line = encode_command("W", 7, *vals, f"{record_crc(vals):04X}")
            if len(line) == 120:
                break
        if len(line) == 120:
            break
    assert len(line) == 120
    board.write(line)
    assert isinstance(_reply(board, 7), Ack)
    longer = encode_command("W", 8, *vals[:14], f"+{vals[14]}", *vals[15:], f"{record_crc(vals):04X}")
    assert len(longer) == 121
    board.write(longer)
    err = board.wait_for(lambda i: isinstance(i, ErrorReply), 5, "LONG")
    assert (err.tag, err.code) == (0, "LONG")


def test_the_deepest_paths_leave_stack_headroom_in_2k_of_ram(tmp_path):
    b = RawBoard(tmp_path, extra=("--stack-report",))
    try:
        _boot(b)
        vals = _record()
        for cmd in [("R", 100), ("G",), ("W", *vals, f"{record_crc(vals):04X}"), ("M", 1),
                    ("K",), ("T",), ("Q",), ("R", "x")]:
            _reply(b, b.send(*cmd))
        b.write(b"$" + b"A" * 200 + b"\n")
        b.wait_for(lambda i: isinstance(i, ErrorReply) and i.code == "LONG", 5, "LONG")
        for cmd in ("N", "F"):
            tag = b.send(cmd, 50)
            from magcal.wire.protocol import FitReply

            b.wait_for(lambda i: isinstance(i, FitReply) and i.tag == tag, 10, f"{cmd} result")
        _reply(b, b.send("Z"))
        b.wait_for(lambda i: isinstance(i, Hello), 5, "hello after Z")
    finally:
        err = b.close()
    m = re.search(r"stack used at most (\d+) bytes; (\d+) bytes of SRAM never touched", err)
    assert m, err
    used, free = int(m.group(1)), int(m.group(2))
    assert free >= 400, f"stack peak {used} bytes leaves only {free} bytes of 2048 untouched"
