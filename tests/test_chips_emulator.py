"""The real firmware on each chip people have: MPU-9150 (AK8975), MPU-9250 (AK8963 at 16 and at
14 bits) and ICM-20948 (AK09916), each under the emulator with that chip's register model.

One board run per chip, spoken to in the wire protocol itself: the hello names the chip and
its resolution, the self-test reads inside that part's datasheet window, the samples are the
chip's own counts, and a calibration record (µT-based, so the same for every chip) written to
the board turns its counts into the calibrated field on the sphere of the Earth field."""

from __future__ import annotations

import time

import numpy as np
import pytest
from firmware_support import require_firmware

from magcal.core.sample import asa_gain
from magcal.devices.emulator import EmulatedBoard, emu_chip
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

pytestmark = pytest.mark.slow

# (chip, bits): WHO_AM_I, the magnetometer's id in the hello, µT per count before ASA, and the
# self-test window in ASA-adjusted counts (AK8975 datasheet MS1187-E-02; AK8963 MS1356-E-02;
# AK09916 as AKM's own driver judges it).
CHIPS = {
    ("mpu9150", 13): (0x68, 0x48, 0.3, ((-100, 100), (-100, 100), (-1000, -300))),
    ("mpu9250", 16): (0x71, 0x48, 0.15, ((-200, 200), (-200, 200), (-3200, -800))),
    ("mpu9250", 14): (0x71, 0x48, 0.6, ((-50, 50), (-50, 50), (-800, -200))),
    ("icm20948", 16): (0xEA, 0x09, 0.15, ((-200, 200), (-200, 200), (-1000, -200))),
}


@pytest.fixture(autouse=True)
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
