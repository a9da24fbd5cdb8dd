"""The real firmware on each chip people have: MPU-9150 (AK8975), MPU-9250 (AK8963 at 16 and at
14 bits) and ICM-20948 (AK09916), each under the emulator with that chip's register model.

One board run per chip, spoken to in the wire protocol itself: the hello names the chip and
its resolution, the self-test reads inside that part's datasheet window, the samples are the
chip's own counts, and a calibration record (µT-based, so the same for every chip) written to
the board turns its counts into the calibrated Earth field put in. Before them, the register
model's chip-specific behaviour the firmware relies on, byte by byte (cheap: no AVR)."""

from __future__ import annotations

import ctypes
import time

import numpy as np
import pytest
from firmware_support import require_firmware

from magcal.core.sample import asa_gain
from magcal.devices.emulator import EmulatedBoard, emu_chip
from magcal.devices.fakebus import _PROVIDER, load_model_library
from magcal.sim.physics import demo_scenario
from magcal.wire.protocol import (
    Ack,
    CalibratedSample,
    Framer,
    Hello,
    RawSample,
    RecordReply,
    encode_command,
    quantize_calibration,
    record_crc,
    record_from_calibration,
)

# (chip, bits): WHO_AM_I, the magnetometer's id in the hello, µT per count before ASA, and the
# self-test window in ASA-adjusted counts (AK8975 datasheet MS1187-E-02; AK8963 MS1356-E-02;
# AK09916 as AKM's own driver judges it).
CHIPS = {
    ("mpu9150", 13): (0x68, 0x48, 0.3, ((-100, 100), (-100, 100), (-1000, -300))),
    ("mpu9250", 16): (0x71, 0x48, 0.15, ((-200, 200), (-200, 200), (-3200, -800))),
    ("mpu9250", 14): (0x71, 0x48, 0.6, ((-50, 50), (-50, 50), (-800, -200))),
    ("icm20948", 16): (0xEA, 0x09, 0.15, ((-200, 200), (-200, 200), (-1000, -200))),
}


MPU_CHIP = {"mpu9150": 0, "mpu9250": 1, "mpu9255": 2, "icm20948": 3}  # mpu9150_model.h


class _Model:
    """The C register model on its own: I2C transfers at a time the test sets, a provider that
    always answers ``counts`` (so the part's range shows)."""

    def __init__(self, chip: str, counts=(32767, -32768, 1234)):
        lib = load_model_library()
        lib.mpu_model_set_chip.restype = ctypes.c_int
        lib.mpu_model_set_chip.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.mpu_model_mag_bits.restype = ctypes.c_int
        lib.mpu_model_mag_bits.argtypes = [ctypes.c_void_p]
        self.lib, self.t_us = lib, 0
        self.mem = ctypes.create_string_buffer(lib.mpu_model_size())

        def provide(_ctx, _t_us, out):
            out[0].hx, out[0].hy, out[0].hz = counts
            return 0

        self._provider = _PROVIDER(provide)  # kept: the C side holds the pointer
        lib.mpu_model_init(self.mem, 0x68, (ctypes.c_uint8 * 3)(170, 180, 190), self._provider, None)
        assert lib.mpu_model_set_chip(self.mem, MPU_CHIP[chip]) == 0

    def write(self, addr: int, reg: int, *data: int) -> bool:
        ok = self.lib.mpu_model_start(self.mem, addr, 0, self.t_us) == 0
        for b in (reg, *data):
            ok = ok and self.lib.mpu_model_write(self.mem, b, self.t_us) == 0
        self.lib.mpu_model_stop(self.mem, self.t_us)
        return ok

    def read(self, addr: int, reg: int, n: int = 1) -> list[int] | None:
        if not self.write(addr, reg):
            return None
        self.lib.mpu_model_start(self.mem, addr, 1, self.t_us)
        out = []
        for _ in range(n):
            b = ctypes.c_uint8()
            self.lib.mpu_model_read(self.mem, ctypes.byref(b), self.t_us)
            out.append(b.value)
        self.lib.mpu_model_stop(self.mem, self.t_us)
        return out

    def measure(self, cntl_reg: int, mode: int, st1_reg: int, data_reg: int, n: int) -> list[int]:
        assert self.write(0x0C, cntl_reg, mode)
        assert self.read(0x0C, st1_reg) == [0]
        self.t_us += 10_000
        assert self.read(0x0C, st1_reg)[0] & 0x01
        b = self.read(0x0C, data_reg, n)
        assert self.read(0x0C, st1_reg)[0] & 0x01 == 0, "reading the data clears DRDY"
        return [int.from_bytes(bytes(b[i:i + 2]), "little", signed=True) for i in (0, 2, 4)] + b[6:]


def test_the_icm20948_answers_in_bank_0_and_its_ak09916_behind_the_bypass():
    m = _Model("icm20948")
    assert m.read(0x68, 0x00) == [0xEA] and m.read(0x68, 0x06) == [0x41]  # asleep after power-up
    assert m.read(0x68, 0x75) == [0x00]  # no MPU WHO_AM_I there
    assert m.write(0x68, 0x7F, 0x20) and m.read(0x68, 0x00) == [0x00]  # bank 2
    assert m.write(0x68, 0x7F, 0x00)
    assert m.write(0x68, 0x0F, 0x02) and m.read(0x0C, 0x00) is None  # bypass, but asleep
    assert m.write(0x68, 0x06, 0x01) and m.read(0x0C, 0x00, 2) == [0x48, 0x09]  # WIA1, WIA2
    assert m.write(0x68, 0x03, 0x20) and m.read(0x0C, 0x00) is None  # I2C_MST_EN takes the bus
    assert m.write(0x68, 0x03, 0x00)
    assert m.write(0x0C, 0x31, 0x0F) and m.read(0x0C, 0x10, 3) == [0, 0, 0]  # no fuse ROM
    # HXL..HZH, TMPS, ST2 in one burst, then back to WIA1: 0x18 wraps to 0x00
    assert m.measure(0x31, 0x01, 0x10, 0x11, 10) == [32752, -32752, 1234, 0, 0, 0x48, 0x09]
    assert m.read(0x0C, 0x31) == [0x00]  # back to power-down by itself
    assert m.write(0x0C, 0x31, 0x10)  # self-test mode: the coil's reading (zero until set)
    m.t_us += 10_000
    assert m.read(0x0C, 0x10)[0] & 0x01 and m.read(0x0C, 0x11, 6) == [0] * 6


def test_the_ak8963_reads_at_the_resolution_cntl1_sets_and_resets_softly():
    m = _Model("mpu9250")
    assert m.read(0x68, 0x75) == [0x71]
    assert m.write(0x68, 0x37, 0x02) and m.read(0x0C, 0x00) == [0x48]
    assert m.write(0x0C, 0x0A, 0x1F) and m.read(0x0C, 0x10, 3) == [170, 180, 190]  # fuse ROM
    assert m.write(0x0C, 0x0A, 0x10)
    assert m.measure(0x0A, 0x11, 0x02, 0x03, 7) == [32760, -32760, 1234, 0x10]  # 16-bit, BITM
    assert m.lib.mpu_model_mag_bits(m.mem) == 16
    assert m.measure(0x0A, 0x01, 0x02, 0x03, 7) == [8190, -8190, 1234, 0x00]  # 14-bit
    assert m.lib.mpu_model_mag_bits(m.mem) == 14
    assert m.write(0x0C, 0x0A, 0x1F) and m.write(0x0C, 0x0B, 0x01)  # CNTL2 SRST
    assert m.read(0x0C, 0x0A) == [0x00]


@pytest.fixture
def _firmware():
    require_firmware()


class _Link:
    """The emulated board's pty, spoken to in protocol lines with no host client in between."""

    def __init__(self, board: EmulatedBoard):
        import serial  # pyserial

        self.board = board
        self.port = serial.Serial(board.start(), 115200, timeout=0.05)
        self.framer = Framer()
        self.tag = 0
        self.measurements: list = []  # every sample line, in order: the i-th is board.served[i]

    def send(self, cmd: str, *args) -> int:
        self.tag += 1
        self.port.write(encode_command(cmd, self.tag, *args))
        return self.tag

    def collect(self, pred, n: int = 1, timeout_s: float = 10.0) -> list:
        got, end = [], time.monotonic() + timeout_s
        while len(got) < n:
            assert time.monotonic() < end, f"only {len(got)} of {n} within {timeout_s} s"
            items = self.framer.feed(self.port.read(4096))
            self.measurements += [m for m in items if isinstance(m, (RawSample, CalibratedSample))]
            got += [m for m in items if pred(m)]
        return got[:n]

    def close(self) -> None:
        self.port.close()
        self.board.stop()


@pytest.mark.slow
@pytest.mark.usefixtures("_firmware")
@pytest.mark.parametrize("chip,bits", list(CHIPS))
def test_each_chip_is_named_self_tested_read_in_its_counts_and_calibrated(tmp_path, chip, bits):
    who, wia, ut_per_count, window = CHIPS[(chip, bits)]
    sc = demo_scenario(4).with_physics(temp_coef_ut_per_c=(0.3, -0.2, 0.1))  # the die's formula counts
    link = _Link(EmulatedBoard(sc, tmp_path / "ee.bin", chip=emu_chip(chip, bits)))
    try:
        hello = link.collect(lambda m: isinstance(m, Hello))[0]
        asa = link.board.scenario.physics.asa
        assert (hello.who_am_i, hello.wia, hello.bits) == (who, wia, bits)
        assert hello.asa == (tuple(asa) if chip != "icm20948" else (128, 128, 128))

        tag = link.send("T")
        reply = link.collect(lambda m: isinstance(m, Ack) and m.tag == tag)[0]
        raw = [int(v) for v in reply.result[:3]]
        adjusted = [r * asa_gain(a) for r, a in zip(raw, hello.asa)]
        assert all(lo <= v <= hi for v, (lo, hi) in zip(adjusted, window)), (raw, adjusted)

        link.send("G")
        samples = link.collect(lambda m: isinstance(m, RawSample), n=40)
        served = list(link.board.served)
        assert [s.raw for s in samples] == [r for (_, _, r, _, _) in served[:40]]
        # the accelerometer's registers, served from the physics' gravity, arrive as read
        assert [s.accel for s in samples] == [link.board.accel(t, k) for (t, k, *_rest) in served[:40]]
        # AK8963 ST2 carries BITM (0x10) at 16-bit output
        assert {s.st2 for s in samples} == {0x10 if (chip, bits) == ("mpu9250", 16) else 0}
        lsb = ut_per_count * np.array([asa_gain(a) for a in hello.asa])
        m_ut, _ = sc.field_ut([t for (t, *_rest) in served[:40]], [k for (_, k, *_rest) in served[:40]])
        assert np.all(np.abs(np.array([s.raw for s in samples]) * lsb - m_ut) <= 0.5 * lsb + 1e-9)

        truth = quantize_calibration(sc.physics.truth())
        record = record_from_calibration(truth)
        tag = link.send("W", *record, f"{record_crc(record):04X}")
        stored = link.collect(lambda m: isinstance(m, RecordReply) and m.tag == tag)[0]
        assert stored.status == "OK" and tuple(stored.values) == record
        link.send("M", 1)
        link.collect(lambda m: isinstance(m, CalibratedSample), n=150)
        # the board's calibrated field is the Earth field the physics put in, sample by sample
        served = list(link.board.served)
        at = [i for i, m in enumerate(link.measurements) if isinstance(m, CalibratedSample)]
        cal = np.array([link.measurements[i].field_nt for i in at]) / 1000.0
        earth = sc.earth_body_ut([served[i][0] for i in at])
        error = np.linalg.norm(cal - earth, axis=1)
        assert np.median(error) < 0.8 + ut_per_count, np.median(error)
    finally:
        link.close()
