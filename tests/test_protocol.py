"""Protocol v1 framing, encoding and calibration records (docs/protocol.md)."""

import numpy as np
import pytest

from magcal.core.calibration import Calibration
from magcal.wire.protocol import (
    Ack,
    Framer,
    Gap,
    Hello,
    ParseError,
    RawSample,
    RecordReply,
    Restart,
    calibration_from_record,
    crc8,
    crc16_ccitt,
    encode_command,
    encode_line,
    parse_command,
    quantize_calibration,
    record_crc,
    record_from_calibration,
)


def hello(seq=0):
    return encode_line("H", [seq, 1, "0.1.0", "68", "48", 176, 178, 166, 100])


def sample(seq, ms=10, raw=(1, 2, 3)):
    return encode_line("S", [seq, ms, *raw, 0, -2150])


def test_check_values_from_the_spec():
    assert crc8(b"123456789") == 0xF4
    assert crc16_ccitt(b"123456789") == 0x29B1


def test_round_trip_of_every_device_message():
    f = Framer()
    data = (
        hello()
        + sample(1)
        + encode_line("A", [2, 7, "R", 50])
        + encode_line("E", [3, 8, "W", "RECCRC"])
        + encode_line("C", [4, 9, "OK", *range(1, 19), "ABCD"])
        + encode_line("L", [5, "booted"])
    )
    out = f.feed(data)
    assert [type(m).__name__ for m in out] == ["Hello", "RawSample", "Ack", "ErrorReply", "RecordReply", "Log"]
    assert out[0].asa == (176, 178, 166) and out[0].who_am_i == 0x68
    assert out[1].raw == (1, 2, 3) and out[1].temp_raw == -2150
    assert out[2] == Ack(2, 7, "R", ("50",))
    assert isinstance(out[4], RecordReply) and out[4].values == tuple(range(1, 19)) and out[4].crc == 0xABCD
    assert f.counters["lines"] == 6


def test_sample_lines_may_carry_the_accelerometer_and_old_ones_still_read():
    """Three trailing fields: the accelerometer's registers (±2 g counts); a line without them
    (an older board, an old capture) reads as before; one or two of them is no sample."""
    f = Framer()
    old, new, cal = f.feed(hello() + encode_line("S", [1, 10, 1, 2, 3, 0, -2150])
                           + encode_line("S", [2, 20, 1, 2, 3, 0, -2150, 120, -340, 16384])
                           + encode_line("U", [3, 30, 1000, 2000, 3000, 0, -2150, 0, 0, -16384, 7]))[1:]
    assert old.raw == (1, 2, 3) and old.accel is None
    assert new.raw == (1, 2, 3) and new.temp_raw == -2150 and new.accel == (120, -340, 16384)
    assert cal.field_nt == (1000, 2000, 3000) and cal.accel == (0, 0, -16384)  # a later field after them: ignored
    for extra in ([5], [5, 6]):
        assert not f.feed(encode_line("S", [4, 40, 1, 2, 3, 0, -2150, *extra]))
    assert f.counters["bad_syntax"] == 2


def test_the_client_puts_the_accelerometer_on_the_sample_in_g_in_the_magnetometer_axes():
    """The line carries the IMU's registers in the IMU's axes; the sample's three are in the
    magnetometer's, the frame of its field (AK8975/AK8963: X↔Y swapped, Z flipped; AK09916: Y, Z flipped)."""
    from magcal.core.chips import ICM20948, MPU9150, MPU9250_16
    from magcal.devices.protocol_client import accel_aux

    m = RawSample(1, 10, (1, 2, 3), 0, 0, (8192, 0, -16384))
    assert accel_aux(m, MPU9150) == {"ax_g": 0.0, "ay_g": 0.5, "az_g": 1.0}
    assert accel_aux(m, MPU9250_16) == {"ax_g": 0.0, "ay_g": 0.5, "az_g": 1.0}
    assert accel_aux(m, ICM20948) == {"ax_g": 0.5, "ay_g": 0.0, "az_g": 1.0}
    assert accel_aux(RawSample(1, 10, (1, 2, 3), 0, 0), MPU9150) == {}


def test_torn_noise_overlong_and_bad_crc_are_counted_not_merged():
    good = sample(2, raw=(7, 8, 9))
    bad_crc = sample(3)[:-3] + b"00\n"
    data = b"\x00\xffnoise" + sample(1)[:12] + good + b"$" + b"9" * 300 + b"\n" + bad_crc + sample(4)
    f = Framer()
    out = f.feed(data)
    raws = [m.raw for m in out if isinstance(m, RawSample)]
    assert raws == [(7, 8, 9), (1, 2, 3)]
    assert f.counters["torn_lines"] == 1
    assert f.counters["overlong_lines"] == 1
    assert f.counters["bad_checksums"] == 1
    assert f.counters["noise_bytes"] > 0


def test_overlong_line_holds_bounded_memory():
    f = Framer()
    f.feed(b"$")
    for _ in range(1000):
        f.feed(b"1" * 1000)
        assert len(f._carry) < 120
    assert f.feed(b"\n" + sample(1)) and f.counters["overlong_lines"] == 1


def test_gaps_and_restarts_are_reported():
    f = Framer()
    out = f.feed(hello(0) + sample(1) + sample(5) + hello(0) + sample(1))
    kinds = [type(m).__name__ for m in out]
    assert kinds == ["Hello", "RawSample", "Gap", "RawSample", "Restart", "Hello", "RawSample"]
    gap = out[2]
    assert gap == Gap(5, 3)
    assert f.counters["lost_lines"] == 3 and f.counters["restarts"] == 1


def test_sequence_wraps_without_a_gap():
    f = Framer()
    out = f.feed(sample(65534) + sample(65535) + sample(0) + sample(1))
    assert not [m for m in out if isinstance(m, (Gap, Restart))]


def test_identity_reply_does_not_count_as_restart():
    f = Framer()
    out = f.feed(hello(0) + sample(1) + encode_line("A", [2, 1, "I"]) + hello(3))
    assert not [m for m in out if isinstance(m, (Gap, Restart))]


def test_lowercase_checksum_and_spaces_are_rejected():
    line = sample(1)
    f = Framer()
    assert not f.feed(line.replace(b"S,1,", b"S, 1,"))
    assert not f.feed(line[:-3] + line[-3:-1].lower() + b"\n") or line[-3:-1] == line[-3:-1].lower()


def test_crlf_is_accepted():
    f = Framer()
    out = f.feed(sample(1)[:-1] + b"\r\n")
    assert isinstance(out[0], RawSample)


def test_commands_parse_and_reject():
    assert parse_command(encode_command("R", 5, 50)) == ("R", 5, (b"50",))
    with pytest.raises(ParseError, match="CRC"):
        parse_command(encode_command("R", 5, 50).replace(b"50", b"51"))
    with pytest.raises(ParseError, match="SYNTAX"):
        parse_command(b"hello\n")
    with pytest.raises(ParseError, match="LONG"):
        parse_command(b"$R," + b"1" * 200 + b"*00\n")
    with pytest.raises(ValueError):
        encode_command("G", 0)


def test_record_round_trip_is_exact_and_crc_protected():
    cal = Calibration(
        offset_ut=[23.5004, -41.2, 12.8],
        field_ut=49.9876,
        soft_iron=[[1.01, 0.002, -0.001], [0.002, 0.99, 0.0005], [-0.001, 0.0005, 1.0]],
        coef_ut_per_unit={"temp_c": [0.05, -0.02, 0.01], "current_a": [0.3, 0.0, -0.4]},
        reference={"temp_c": 25.0},
    )
    values = record_from_calibration(cal)
    assert len(values) == 18 and values[0] == 1
    back = calibration_from_record(values)
    assert record_from_calibration(back) == values
    assert back.close_to(cal, atol_ut=6e-4, atol_w=6e-7)
    assert record_from_calibration(quantize_calibration(back)) == values
    crc = record_crc(values)
    changed = list(values)
    changed[3] += 1
    assert record_crc(changed) != crc


def test_record_refuses_what_v1_cannot_carry():
    cal = Calibration([0, 0, 0], 50.0, coef_ut_per_unit={"t_s": [0.001, 0, 0]})
    with pytest.raises(ValueError, match="t_s"):
        record_from_calibration(cal)
