"""The MotionCal / Adafruit convention, pure part: lines, framing, packet, echo, offline logs."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal.app.load import load_motioncal_log
from magcal.core.calibration import Calibration
from magcal.core.errors import InputError
from magcal.sim.physics import Motion, Physics, Scenario
from magcal.wire import motioncal as mc


def random_cal(rng, field_ut=None) -> Calibration:
    a = rng.normal(0, 0.08, (3, 3))
    w = np.eye(3) + 0.5 * (a + a.T)
    return Calibration(
        offset_ut=rng.uniform(-150, 150, 3),
        field_ut=rng.uniform(20, 70) if field_ut is None else field_ut,
        soft_iron=w,
    )


def device_print(values, decimals) -> str:
    """Format numbers the way the Arduino sketches print them (fixed decimals)."""
    return ",".join(f"{v:.{decimals}f}" for v in values)


def echo_lines(packet: bytes) -> tuple[mc.CalLine, mc.CalLine]:
    """The Cal1/Cal2 lines an Adafruit sketch prints after storing ``packet``."""
    f = struct.unpack("<16f", packet[2:66])
    full = [f[10], f[13], f[14], f[13], f[11], f[15], f[14], f[15], f[12]]
    return (
        mc.parse_line("Cal1:" + device_print(f[:10], 3)),
        mc.parse_line("Cal2:" + device_print(full, 4)),
    )


# -- CRC and packet -----------------------------------------------------------------------
def test_crc16_is_the_modbus_crc():
    # published check value of CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF)
    assert mc.crc16(b"123456789") == 0x4B37


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_packet_layout_crc_and_round_trip(seed):
    rng = np.random.default_rng(seed)
    cal = random_cal(rng)
    acc, gyr = rng.normal(0, 0.2, 3), rng.normal(0, 0.01, 3)
    pkt = mc.encode_packet(cal, acc, gyr)
    assert len(pkt) == 68 and pkt[:2] == bytes((117, 84))
    assert mc.crc16(pkt) == 0
    assert mc.crc16(pkt[:66]) == pkt[66] | (pkt[67] << 8)  # low byte first
    vals = mc.decode_packet(pkt)
    w = cal.soft_iron
    expect = [*acc, *gyr, *cal.offset_ut, cal.field_ut, w[0, 0], w[1, 1], w[2, 2], w[0, 1], w[0, 2], w[1, 2]]
    assert np.allclose(vals, np.float32(expect), rtol=0, atol=0)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), bit=st.integers(0, 68 * 8 - 1))
def test_any_single_bit_error_is_caught(seed, bit):
    pkt = bytearray(mc.encode_packet(random_cal(np.random.default_rng(seed))))
    pkt[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(ValueError, match="CRC|signature"):
        mc.decode_packet(bytes(pkt))


def test_decode_names_the_problem():
    pkt = mc.encode_packet(Calibration(offset_ut=[1, 2, 3], field_ut=50))
    with pytest.raises(ValueError, match="68 bytes"):
        mc.decode_packet(pkt[:67])
    with pytest.raises(ValueError, match="signature"):
        mc.decode_packet(b"uX" + pkt[2:])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_soft_iron_mapping_inverts_the_forward_model(seed):
    """What the device computes from the packet, invW·(m − V), undoes Calibration.distort."""
    rng = np.random.default_rng(seed)
    cal = random_cal(rng)
    h = rng.normal(size=(200, 3))
    h *= cal.field_ut / np.linalg.norm(h, axis=1, keepdims=True)
    m = cal.distort(h)
    got = mc.apply_like_device(mc.decode_packet(mc.encode_packet(cal)), m)
    # float32 in the packet: relative 1e-7 of |m| (≤ ~250 µT) and of W
    assert np.abs(got - h).max() < 2e-4


def test_soft_iron_mapping_is_not_blind_to_the_matrix_order():
    """Two off-diagonal entries swapped in the packet would not undo the distortion. A fixed
    calibration: on a random one the two entries can come out (almost) equal, and then the swap
    changes nothing."""
    cal = Calibration(offset_ut=[12.0, -30.0, 8.0], field_ut=48.0,
                      soft_iron=[[1.03, 0.02, -0.01], [0.02, 0.97, 0.04], [-0.01, 0.04, 1.01]])
    rng = np.random.default_rng(3)
    h = rng.normal(size=(200, 3))
    h *= cal.field_ut / np.linalg.norm(h, axis=1, keepdims=True)
    m = cal.distort(h)
    packet = mc.decode_packet(mc.encode_packet(cal))
    assert np.abs(mc.apply_like_device(packet, m) - h).max() < 2e-4
    wrong = packet[:13] + (packet[14], packet[13], packet[15])
    assert packet[13] != packet[14] and np.abs(mc.apply_like_device(wrong, m) - h).max() > 1e-3


def test_calibration_with_extra_terms_is_refused():
    cal = Calibration(offset_ut=[1, 2, 3], field_ut=50, coef_ut_per_unit={"temp_c": [0.1, 0, 0]})
    with pytest.raises(ValueError, match="temp_c"):
        mc.encode_packet(cal)


# -- lines ----------------------------------------------------------------------------------
@pytest.mark.parametrize("ending", ["\r", "\n", "\r\n", ""])
def test_raw_line_with_any_ending(ending):
    line = mc.parse_line(f"Raw:-12,40,8190,3,-2,1,235,-412,-1280{ending}")
    assert isinstance(line, mc.RawLine)
    assert line.accel_counts == (-12, 40, 8190) and line.gyro_counts == (3, -2, 1)
    assert line.field_ut == pytest.approx((23.5, -41.2, -128.0))


def test_uni_line_carries_microtesla():
    line = mc.parse_line(b"Uni:0.12,-0.05,9.79,0.0012,-0.0031,0.0000,23.47,-41.23,12.81\r\n")
    assert isinstance(line, mc.UniLine)
    assert line.field_ut == pytest.approx((23.47, -41.23, 12.81))
    assert line.accel_ms2[2] == pytest.approx(9.79)


def test_cal_lines_keep_their_printed_precision():
    c1 = mc.parse_line("Cal1:0.000,0.000,0.000,0.000,0.000,0.000,23.500,-41.200,12.800,48.250")
    c2 = mc.parse_line("Cal2:1.0123,0.0040,-0.0030,0.0040,0.9910,0.0020,-0.0030,0.0020,1.0040")
    assert c1.kind == 1 and len(c1.values) == 10 and set(c1.decimals) == {3}
    assert c2.kind == 2 and set(c2.decimals) == {4}
    cal = mc.calibration_from_echo(c1, c2)
    assert cal.offset_ut == pytest.approx([23.5, -41.2, 12.8]) and cal.field_ut == 48.25
    assert cal.soft_iron[0, 1] == pytest.approx(0.004)


@pytest.mark.parametrize(
    "text,reason",
    [
        ("Raw:1,2,3,4,5,6,7,8", "malformed"),  # 8 values
        ("Raw:1,2,3,4,5,6,7,8,9,10", "malformed"),
        ("Raw:1,2,3,4,5,6,7.5,8,9", "malformed"),  # Raw: is integers
        ("Raw:1,2,3,4,5,6,7,8,99999", "int16"),
        ("Raw:1,2,3,4,5,6,7,8Raw:1,2,3,4,5,6,7,8,9", "malformed"),  # torn and glued
        ("Uni:1.0,2.0,3.0", "malformed"),
        ("Cal1:1.000,2.000", "malformed"),
        ("Cal1:0.000,0.000,0.000,0.000,0.000,0.000,23.500,-41.200,12.800,48.2", "torn"),
    ],
)
def test_broken_lines_never_become_readings(text, reason):
    line = mc.parse_line(text)
    assert isinstance(line, mc.OtherLine) and reason in line.reason


def test_noise_ahead_of_a_line_is_skipped_and_plain_text_is_other():
    assert isinstance(mc.parse_line(b"\xff\x07#Raw:1,2,3,4,5,6,7,8,9"), mc.RawLine)
    other = mc.parse_line("Wrote calibration")
    assert isinstance(other, mc.OtherLine) and other.reason == ""


@settings(max_examples=80, deadline=None)
@given(
    ending=st.sampled_from([b"\r", b"\n", b"\r\n"]),
    cuts=st.lists(st.integers(0, 400), max_size=12),
)
def test_splitter_gives_the_same_lines_for_any_chunking(ending, cuts):
    lines = [b"Raw:1,2,3,4,5,6,7,8,9", b"Uni:0.10,0.20,9.80,0.0000,0.0000,0.0000,1.00,2.00,3.00",
             b"Cal1:0.000,0.000,0.000,0.000,0.000,0.000,1.000,2.000,3.000,50.000", b"hello"]
    data = ending.join(lines) + ending
    sp = mc.LineSplitter()
    got = []
    prev = 0
    for c in sorted(set(min(c, len(data)) for c in cuts)) + [len(data)]:
        got += sp.feed(data[prev:c])
        prev = c
    assert got == lines


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=600))
def test_arbitrary_bytes_never_raise_and_only_whole_lines_become_readings(data):
    sp, asm = mc.LineSplitter(), mc.SampleAssembler()
    for line in sp.feed(data + b"\n"):
        parsed = mc.parse_line(line)
        f = asm.push(parsed)
        if f is not None:
            assert isinstance(parsed, (mc.RawLine, mc.UniLine)) and len(f) == 3
    assert asm.counters["lines"] == asm.counters["raw"] + asm.counters["uni"] + asm.counters["junk"] \
        + asm.counters["cal1"] + asm.counters["cal2"]


def test_splitter_drops_overlong_runs():
    sp = mc.LineSplitter()
    got = sp.feed(b"x" * 1000 + b"\r\nRaw:1,2,3,4,5,6,7,8,9\r\n")
    assert got == [b"Raw:1,2,3,4,5,6,7,8,9"] and sp.counters["overlong"] == 1


def test_assembler_one_sample_per_reading_preferring_uni():
    asm = mc.SampleAssembler()
    stream = [
        "Adafruit AHRS - IMU Calibration!",
        "Raw:0,0,8192,0,0,0,235,-412,128", "Uni:0.00,0.00,9.80,0.0000,0.0000,0.0000,23.54,-41.27,12.86",
        "Raw:0,0,8192,0,0,0,236,-413,129", "Uni:0.00,0.00,9.80,0.0000,0.0000,0.0000,23.61,-41.33,12.94",
        "Cal1:0.000,0.000,0.000,0.000,0.000,0.000,0.000,0.000,0.000,50.000",
        "Raw:0,0,8192,0,0,0,237,-414,130", "Uni:0.00,0.00,9.80,0.0000,0.0000,0.0000,23.77,-41.44,13.01",
    ]
    out = [f for f in (asm.push(mc.parse_line(s)) for s in stream) if f is not None]
    # the first reading comes from Raw: (no Uni: seen yet), then Uni: carries the readings
    assert out == [pytest.approx((23.5, -41.2, 12.8)), (23.61, -41.33, 12.94), (23.77, -41.44, 13.01)]
    assert asm.counters["junk"] == 1 and asm.counters["cal1"] == 1 and asm.last_cal1 is not None


def test_assembler_raw_only_device():
    asm = mc.SampleAssembler()
    out = [asm.push(mc.parse_line(f"Raw:0,0,0,0,0,0,{i},{-i},7")) for i in range(5)]
    assert out == [pytest.approx((0.1 * i, -0.1 * i, 0.7)) for i in range(5)]


# -- the echo -------------------------------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_faithful_echo_matches_and_a_changed_one_does_not(seed):
    rng = np.random.default_rng(seed)
    cal = random_cal(rng)
    sent = mc.packet_values(cal)
    pkt = mc.encode_packet(cal)
    c1, c2 = echo_lines(pkt)
    assert mc.compare_echo(sent, c1, c2) == []
    echoed = mc.calibration_from_echo(c1, c2)
    assert echoed.close_to(cal, **mc.compare_tolerance())
    # one value off by two units of its last printed digit is reported, by name
    i = int(rng.integers(6, 16))
    vals, _ = mc.echo_values(c1, c2)
    bumped = list(struct.unpack("<16f", pkt[2:66]))
    bumped[i] += 2e-3 if i < 10 else 2e-4
    b1, b2 = echo_lines(pkt[:2] + struct.pack("<16f", *bumped) + pkt[66:])
    diff = mc.compare_echo(sent, b1, b2)
    assert diff and diff[0].startswith(mc.PACKET_NAMES[i])


def test_small_offsets_pass_at_printed_precision_where_a_fixed_tolerance_fails():
    """MotionCal accepts |echo − sent| ≤ 1e-4 + 3e-5·|x|; a 3-decimal echo of 0.0004 µT cannot."""
    cal = Calibration(offset_ut=[0.0004, -0.0003, 12.3456], field_ut=47.0)
    sent = mc.packet_values(cal)
    c1, c2 = echo_lines(mc.encode_packet(cal))
    assert c1.values[6] == 0.0 and abs(c1.values[6] - sent[6]) > 1e-4 + 3e-5 * abs(sent[6])
    assert mc.compare_echo(sent, c1, c2) == []


def test_nan_echo_never_matches():
    cal = Calibration(offset_ut=[1, 2, 3], field_ut=50)
    c1 = mc.parse_line("Cal1:0.000,0.000,0.000,0.000,0.000,0.000,nan,2.000,3.000,50.000")
    c2 = mc.parse_line("Cal2:1.0000,0.0000,0.0000,0.0000,1.0000,0.0000,0.0000,0.0000,1.0000")
    assert isinstance(c1, mc.CalLine)
    assert any(d.startswith("hard_iron_x") for d in mc.compare_echo(mc.packet_values(cal), c1, c2))
    assert mc.calibration_from_echo(c1, c2) is None


# -- auto-detection -------------------------------------------------------------------------
def test_looks_like_motioncal():
    adafruit = ["Adafruit AHRS - IMU Calibration!", "Raw:1,2,3,4,5,6,7,8,9",
                "Uni:0.10,0.20,9.80,0.0000,0.0000,0.0000,1.00,2.00,3.00"]
    assert mc.looks_like_motioncal(adafruit)
    assert mc.looks_like_motioncal([s.encode() + b"\r" for s in adafruit])
    assert not mc.looks_like_motioncal(["$H,0,1,0.3.0,68,48,176,178,166,50*1F", "$S,1,20,1,2,3,0,100*A0"])
    assert not mc.looks_like_motioncal(["Adafruit AHRS - IMU Calibration!", "Raw:1,2,3"])
    assert not mc.looks_like_motioncal([])


# -- offline logs ---------------------------------------------------------------------------
def _log_scenario() -> Scenario:
    return Scenario(
        physics=Physics(field_ut=50.0, hard_iron_ut=(12.0, -30.0, 5.0), noise_ut=0.2),
        motion=Motion("sphere", period_s=10.0),
        seed=11,
    )


def test_load_log_reads_raw_lines_with_mixed_endings_and_junk(tmp_path):
    run = _log_scenario().simulate(300, rate_hz=50)
    m = run.series.field_ut
    parts = [b"MotionCal log\r\n", b"\r\n"]
    expect_rows = []
    for i, v in enumerate(m):
        ending = (b"\r", b"\n", b"\r\n")[i % 3]
        if i % 50 == 7:
            parts.append(b"Raw:1,2,3" + ending)  # torn
        c = np.round(v * 10).astype(int)
        expect_rows.append(sum(p.count(b"\n") + p.count(b"\r") - p.count(b"\r\n") for p in parts))
        parts.append(b"Raw:0,0,8192,0,0,0,%d,%d,%d" % tuple(c) + ending)
    path = tmp_path / "motioncal.log"
    path.write_bytes(b"".join(parts))
    s = load_motioncal_log(path)
    assert len(s) == len(m)
    assert np.allclose(s.field_ut, np.round(m * 10) / 10, atol=1e-9)
    assert np.array_equal(s.t_s, np.arange(len(m)))  # no time in the convention: index
    assert list(s.row) == expect_rows
    s50 = load_motioncal_log(path, rate_hz=50)
    assert s50.t_s[-1] == pytest.approx((len(m) - 1) / 50)


def test_load_log_without_readings_names_the_file(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("time,x,y,z\n1,2,3,4\n")
    with pytest.raises(InputError, match="notes.txt.*no Raw"):
        load_motioncal_log(p)
    with pytest.raises(InputError, match="cannot read"):
        load_motioncal_log(tmp_path / "missing.log")


def test_serial_monitor_timestamps_ahead_of_lines_are_tolerated():
    """The Arduino IDE's serial monitor can prefix every line with 'hh:mm:ss.mmm -> '."""
    data = (b"12:00:00.001 -> Adafruit AHRS - IMU Calibration!\n"
            b"12:00:00.011 -> Raw:0,0,8192,0,0,0,235,-412,128\n"
            b"12:00:00.012 -> Uni:0.00,0.00,9.80,0.0000,0.0000,0.0000,23.54,-41.27,12.86\n"
            b"12:00:00.021 -> Raw:0,0,8192,0,0,0,236,-413,129\n"
            b"12:00:00.022 -> Uni:0.00,0.00,9.80,0.0000,0.0000,0.0000,23.61,-41.33,12.94\n")
    assert mc.looks_like_motioncal(data.splitlines())
    s = mc.parse_log(data)
    assert np.allclose(s.field_ut, [[23.5, -41.2, 12.8], [23.61, -41.33, 12.94]])
    assert list(s.row) == [1, 4]
