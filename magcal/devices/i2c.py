"""The ``i2c:`` backend: an MPU-9150, MPU-9250/9255 or ICM-20948 straight on a Linux I2C bus
(smbus2), no Arduino. Which one is there is found by its ids (``magcal.core.chips``).

Port strings: ``i2c:1`` (``/dev/i2c-1``), ``i2c:/dev/i2c-1``, ``i2c:1?addr=0x69`` (AD0 high),
``i2c:1?addr=0x69&rate=50``, ``i2c:1?bits=14`` (an MPU-9250's AK8963 at 14 bits; 16 otherwise),
``i2c:1?chip=icm20948`` (refuse any other part).

The ICM-20948 is told apart by its bank-0 WHO_AM_I (0x00 = 0xEA) when 0x75 reads no MPU id; its
bypass is bank 0 ``INT_PIN_CFG`` 0x0F, and its AK09916 answers at 0x0C with WIA2 (0x01) = 0x09,
ST1 0x10, data 0x11–0x16 (little-endian) and ST2 0x18 read after the data, CNTL2 0x31, no ASA.

What the host does (register facts: ``docs/hardware.md``, AK8975 datasheet MS1187-E-02):

1. Bring-up: ``WHO_AM_I`` (0x75) must read 0x68 (whatever AD0 is); reset (``PWR_MGMT_1`` =
   0x80, 100 ms), wake with the X-gyro clock (0x01), clear ``I2C_MST_EN`` in ``USER_CTRL``,
   set ``I2C_BYPASS_EN`` in ``INT_PIN_CFG``; now the AK8975 answers at 0x0C and ``WIA`` must
   read 0x48. ASA bytes from the fuse ROM (``CNTL`` = 0x0F, read 0x10..0x12, power down).
2. Each measurement: ``CNTL`` = 0x01 (single), poll ``ST1.DRDY`` on the monotonic clock until a
   deadline, then ONE burst read of HXL..ST2 (7 bytes; reading ST2 ends the measurement) and
   the MPU's ``TEMP_OUT``. DERR/HOFL/rail/all-zero readings are rejected: counted in
   ``counters`` and reported as ``Event("rejected")``.
3. Calibration lives in the host-side store (``magcal.devices.host_store``): the AK8975 has no
   offset registers.

Time comes from an injectable ``clock`` (seconds, monotonic) and ``sleep`` pair; a simulated
bus (``magcal.devices.fakebus.FakeBus``) brings its own simulated clock, which the backend uses
unless told otherwise, so tests and the CLI run against it fast and deterministically.
"""

from __future__ import annotations

import errno
import re
import time
from dataclasses import dataclass, replace
from typing import Callable, Iterable

from ..core.chips import CHIPS, ICM20948, MPU9150, NEUTRAL_ASA, Chip, Magnetometer, chip_named
from ..core.errors import DeviceError, IdentityError, NoReply, PortUnavailable
from ..core.sample import ST2_DERR, ST2_HOFL, Sample, asa_gain, temp_raw_to_c
from ..core.selftest import SELF_TEST_WINDOW, SelfTestResult  # noqa: F401 (SELF_TEST_WINDOW: re-exported)
from ..wire.dialect import Dialect
from .base import Abilities, Device, Event, Identity, Item
from .host_store import HostStore
from .port import MPU_ADDRS, Port, check_rate, chip_of

# -- registers ---------------------------------------------------------------------------------
MPU_WHO_AM_I_VALUE = 0x68
REG_INT_PIN_CFG = 0x37
REG_TEMP_OUT_H = 0x41
REG_USER_CTRL = 0x6A
REG_PWR_MGMT_1 = 0x6B
REG_WHO_AM_I = 0x75
BIT_I2C_BYPASS_EN = 0x02
BIT_I2C_MST_EN = 0x20

AK_ADDR = 0x0C
AK_WIA_VALUE = 0x48
REG_WIA = 0x00
REG_ST1 = 0x02
REG_HXL = 0x03
REG_CNTL = 0x0A
REG_ASTC = 0x0C
REG_ASAX = 0x10
ST1_DRDY = 0x01
ASTC_SELF = 0x40
MODE_POWER_DOWN = 0x00
MODE_SINGLE = 0x01
MODE_SELF_TEST = 0x08
MODE_FUSE_ROM = 0x0F
AK8963_BIT_16 = 0x10  # CNTL1 BIT: 16-bit output


@dataclass(frozen=True)
class ImuRegisters:
    """Where an IMU keeps what the host touches (the ICM-20948's are bank 0)."""

    who_am_i: int
    pwr_mgmt_1: int
    user_ctrl: int
    int_pin_cfg: int
    temp_out_h: int


@dataclass(frozen=True)
class MagRegisters:
    """Where a magnetometer keeps its id, status, data and mode (``burst``: data through ST2)."""

    id_reg: int
    st1: int
    data: int
    burst: int
    cntl: int
    astc: int | None
    mode_self_test: int


MPU_REGS = ImuRegisters(REG_WHO_AM_I, REG_PWR_MGMT_1, REG_USER_CTRL, REG_INT_PIN_CFG, REG_TEMP_OUT_H)
ICM_REGS = ImuRegisters(0x00, 0x06, 0x03, 0x0F, 0x39)  # DS-000189 user bank 0
REG_BANK_SEL_ICM = 0x7F
AK89XX_REGS = MagRegisters(REG_WIA, REG_ST1, REG_HXL, 7, REG_CNTL, REG_ASTC, MODE_SELF_TEST)
AK09916_REGS = MagRegisters(0x01, 0x10, 0x11, 8, 0x31, None, 0x10)  # WIA2, ST1, HXL, +TMPS+ST2, CNTL2

# -- timing (seconds) ------------------------------------------------------------------------------
RESET_WAIT_S = 0.100
MST_DISABLE_WAIT_S = 0.003
MODE_CHANGE_WAIT_S = 0.0001  # ≥ 100 µs between CNTL modes (datasheet)
MEASURE_MIN_S = 0.007  # no point polling DRDY sooner; the measurement takes ~7–9 ms
DRDY_POLL_S = 0.0005
DRDY_TIMEOUT_S = 0.050  # five times the worst measurement time any driver assumes
MAX_CONSECUTIVE_DRDY_MISSES = 3
MAX_CONSECUTIVE_BUS_ERRORS = 5
DEFAULT_RATE_HZ = 50


NACK_ERRNOS = (errno.EREMOTEIO, errno.ENXIO, errno.EIO)


class MagnetometerMissing(DeviceError):
    """The MPU answered but the AK8975 at 0x0C did not, even with the I2C bypass on."""


class DataNotReady(NoReply):
    """The AK8975 never raised DRDY within the deadline: a stuck or absent measurement."""


# -- the port string ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class I2CAddress:
    bus: int | str  # what smbus2.SMBus takes: a number or a device path
    path: str  # the device file, for messages
    address: int
    rate_hz: int
    bits: int | None = None  # the AK8963's resolution, when the port string asks for one


    @classmethod
    def of(cls, port: Port) -> "I2CAddress":
        """Where an ``i2c:`` port string points: ``i2c:1``, ``i2c:/dev/i2c-1``, ``i2c:1?addr=0x69``."""
        where = port.target
        if re.fullmatch(r"\d+", where):
            bus: int | str = int(where)
            path = f"/dev/i2c-{bus}"
        else:
            path = where
            m = re.fullmatch(r"/dev/i2c-(\d+)", where)
            bus = int(m.group(1)) if m else where
        return cls(bus=bus, path=path, address=port.get("addr", MPU_ADDRS[0]), rate_hz=port.get("rate", DEFAULT_RATE_HZ),
                   bits=port.get("bits"))


def _default_bus_factory(bus):
    try:
        import smbus2
    except ImportError:
        raise DeviceError("the i2c: backend needs smbus2 (pip install 'magcal-mpu9150[i2c]')") from None
    return smbus2.SMBus(bus)


def open_bus(factory: Callable, where: I2CAddress):
    """``factory(bus)``, with the operating system's refusals turned into what to do about them."""
    try:
        return factory(where.bus)
    except FileNotFoundError:
        raise PortUnavailable(
            f"{where.path} does not exist: I2C bus {where.bus} is not available. "
            "Enable I2C (Raspberry Pi: raspi-config → Interface Options → I2C, or "
            "dtparam=i2c_arm=on in config.txt, then reboot) and check the bus number with "
            "ls /dev/i2c-*"
        ) from None
    except PermissionError:
        raise PortUnavailable(
            f"{where.path}: permission denied (add your user to the 'i2c' group, then log in again)"
        ) from None
    except OSError as exc:
        raise PortUnavailable(f"{where.path}: cannot open ({exc})") from None


def _int16(lo: int, hi: int) -> int:
    v = (hi << 8) | lo
    return v - 0x10000 if v & 0x8000 else v


# -- bring-up: which chip, and its registers ------------------------------------------------------
class ChipBringUp:
    """Finding which chip is on the bus and setting it up: the register traffic of bring-up,
    for the device below (which owns the bus, the clock and the port)."""

    bus: object
    where: I2CAddress
    chip: Chip
    expected: Chip | None
    sleep: Callable[[float], None]

    def _rb(self, addr: int, reg: int) -> int:
        return int(self.bus.read_byte_data(addr, reg))

    def _wb(self, addr: int, reg: int, value: int) -> None:
        self.bus.write_byte_data(addr, reg, value & 0xFF)

    def _block(self, addr: int, reg: int, n: int) -> list[int]:
        return [int(b) for b in self.bus.read_i2c_block_data(addr, reg, n)]

    @property
    def imu(self) -> ImuRegisters:
        return ICM_REGS if self.chip.magnetometer is Magnetometer.AK09916 else MPU_REGS

    @property
    def mag(self) -> MagRegisters:
        return AK09916_REGS if self.chip.magnetometer is Magnetometer.AK09916 else AK89XX_REGS

    def _mode_bits(self, mode: int) -> int:
        """The mode with the AK8963's 16-bit BIT when this chip reads at 16 bits."""
        sixteen = self.chip.magnetometer is Magnetometer.AK8963 and self.chip.bits == 16
        return mode | AK8963_BIT_16 if sixteen and mode not in (MODE_POWER_DOWN, MODE_FUSE_ROM) else mode

    def _ak_mode(self, mode: int) -> None:
        """Change CNTL through power-down, as the datasheet requires."""
        self._wb(AK_ADDR, self.mag.cntl, MODE_POWER_DOWN)
        self.sleep(MODE_CHANGE_WAIT_S)
        if mode != MODE_POWER_DOWN:
            self._wb(AK_ADDR, self.mag.cntl, self._mode_bits(mode))

    def _identify_imu(self) -> int:
        """WHO_AM_I at 0x75 (the MPUs), else bank-0 0x00 (the ICM-20948); sets ``self.chip``."""
        path, mpu = self.where.path, self.where.address
        try:
            who = self._rb(mpu, REG_WHO_AM_I)
        except OSError as exc:
            other = MPU_ADDRS[1] if mpu == MPU_ADDRS[0] else MPU_ADDRS[0]
            raise PortUnavailable(
                f"{path}: nothing answers at 0x{mpu:02X} ({exc.strerror or exc}); check wiring "
                f"and power, or try addr=0x{other:02X} (AD0 {'high' if other == 0x69 else 'low'})"
            ) from None
        if not any(who in c.who_am_i for c in CHIPS if c is not ICM20948):
            who = self._icm_who_am_i(who)
        found = [c for c in CHIPS if who in c.who_am_i]
        expected = self.expected
        if expected is not None and who not in expected.who_am_i:
            raise IdentityError(f"{path} 0x{mpu:02X}: WHO_AM_I reads 0x{who:02X}, expected "
                                f"0x{expected.who_am_i[0]:02X} ({expected.label.split(' ')[0]})")
        if not found:
            raise IdentityError(
                f"{path} 0x{mpu:02X}: WHO_AM_I reads 0x{who:02X}, which no supported chip has "
                "(0x68 MPU-9150, 0x71/0x73 MPU-9250/9255, 0xEA ICM-20948 at bank-0 0x00)"
            )
        self.chip = expected or self._chip_at_bits(found[0])
        return who

    def _icm_who_am_i(self, who_75: int) -> int:
        """0xEA when bank 0's 0x00 says ICM-20948; else what 0x75 read (no bank to select)."""
        mpu = self.where.address
        try:
            self._wb(mpu, REG_BANK_SEL_ICM, 0x00)
            who = self._rb(mpu, ICM_REGS.who_am_i)
        except OSError:
            return who_75
        return who if who in ICM20948.who_am_i else who_75

    def _chip_at_bits(self, chip: Chip) -> Chip:
        """The row for the resolution the port asks for (``bits=``, the AK8963 only)."""
        bits = self.where.bits
        try:
            return chip if bits is None else chip_named(chip.name, bits)
        except ValueError as exc:
            raise IdentityError(f"{self.where.path}: found the {chip.label}, but {exc}") from None

    def _open_bypass(self) -> None:
        """Reset, wake, stop the IMU's own I2C master and let the magnetometer onto the bus."""
        mpu, regs = self.where.address, self.imu
        try:
            self._wb(mpu, regs.pwr_mgmt_1, 0x80)  # device reset
            self.sleep(RESET_WAIT_S)
            self._wb(mpu, regs.pwr_mgmt_1, 0x01)  # wake, best clock source
            user = self._rb(mpu, regs.user_ctrl)
            self._wb(mpu, regs.user_ctrl, user & ~BIT_I2C_MST_EN)
            self.sleep(MST_DISABLE_WAIT_S)
            self._wb(mpu, regs.int_pin_cfg, BIT_I2C_BYPASS_EN)
        except OSError as exc:
            raise PortUnavailable(f"{self.where.path} 0x{mpu:02X}: bring-up failed ({exc})") from None

    def _identify_magnetometer(self, who: int) -> int:
        path, mpu, name = self.where.path, self.where.address, self.chip.magnetometer.value
        imu = self.chip.label.split(" ")[0]
        try:
            wia = self._rb(AK_ADDR, self.mag.id_reg)
        except OSError as exc:
            raise MagnetometerMissing(
                f"{path}: the {imu} answers at 0x{mpu:02X} but the {name} at 0x0C does not "
                f"({exc.strerror or exc}) with the I2C bypass on; is this an MPU-6050 (no magnetometer)?"
            ) from None
        if wia != self.chip.mag_id:
            reg = "WIA2" if self.chip.magnetometer is Magnetometer.AK09916 else "WIA"
            raise IdentityError(f"{path} 0x0C: {reg} reads 0x{wia:02X}, expected 0x{self.chip.mag_id:02X} ({name})")
        return wia

    def _read_asa(self) -> tuple[int, int, int]:
        try:
            self._ak_mode(MODE_FUSE_ROM)
            self.sleep(MODE_CHANGE_WAIT_S)
            asa = self._block(AK_ADDR, REG_ASAX, 3)
            self._ak_mode(MODE_POWER_DOWN)
        except OSError as exc:
            raise DeviceError(f"{self.where.path} 0x0C: reading the ASA fuse ROM failed ({exc})") from None
        return (asa[0], asa[1], asa[2])


# -- the device ---------------------------------------------------------------------------------------
class I2CDevice(ChipBringUp, HostStore, Device):
    """An MPU-9150 + AK8975 on a Linux I2C bus, measured one single shot at a time; its
    calibration lives in the host-side store (``HostStore``): the AK8975 has no offset registers."""

    abilities = Abilities(live=True, store=True, self_test=True)

    def __init__(
        self,
        port: Port,
        bus_factory: Callable | None = None,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], None] | None = None,
        store_dir=None,
        drdy_timeout_s: float = DRDY_TIMEOUT_S,
    ):
        super().__init__(port.url, clock or time.monotonic)
        self.where = I2CAddress.of(port)
        self._bus_factory = bus_factory or _default_bus_factory
        self._clock_arg, self._sleep_arg = clock, sleep
        self.sleep: Callable[[float], None] = sleep or time.sleep
        self.store_dir = store_dir
        self.drdy_timeout_s = float(drdy_timeout_s)
        self.bus = None
        self.asa: tuple[int, int, int] = (128, 128, 128)
        self.expected: Chip | None = chip_of(port) if port.get("chip") else None
        self.chip: Chip = self.expected or MPU9150
        self.rate_hz = self.where.rate_hz
        self._running = False
        self._next_due = 0.0
        self._seq = 0
        self._drdy_misses = 0
        self._bus_errors = 0

    # -- bus access -----------------------------------------------------------------------------
    def _connect(self):
        bus = open_bus(self._bus_factory, self.where)
        # A simulated bus carries its own simulated time; use it unless the caller chose.
        sim_clock = getattr(bus, "clock", None)
        if self._clock_arg is None and callable(sim_clock):
            self.clock = sim_clock
            if self._sleep_arg is None and callable(getattr(sim_clock, "sleep", None)):
                self.sleep = sim_clock.sleep
        return bus

    # -- bring-up -------------------------------------------------------------------------------
    def _open(self) -> Identity:
        self.bus = self._connect()
        try:
            return self._bring_up()
        except BaseException:
            self._close_bus()
            raise

    def _bring_up(self) -> Identity:
        path, mpu = self.where.path, self.where.address
        who = self._identify_imu()
        self._open_bypass()
        wia = self._identify_magnetometer(who)
        self.asa = self._read_asa() if self.chip.has_asa else NEUTRAL_ASA
        return Identity(transport="i2c", proto=0, firmware="", who_am_i=who, wia=wia, asa=self.asa,  # proto 0: no wire
                        rate_hz=self.rate_hz, extra={"bus": path, "address": f"0x{mpu:02X}"}, bits=self.chip.bits)

    # -- streaming --------------------------------------------------------------------------------
    def set_rate(self, rate_hz: int) -> int:
        self.rate_hz = check_rate(rate_hz, self.url)
        if self.identity is not None:
            self.identity = replace(self.identity, rate_hz=self.rate_hz)
        return self.rate_hz

    def _start(self, rate_hz: int | None) -> None:
        self._require_open()
        if rate_hz is not None:
            self.set_rate(rate_hz)
        self._running = True
        self._next_due = self.clock()

    def _stop(self) -> None:
        self._running = False

    def _receive(self, wait_s: float) -> Iterable[Item]:
        self._require_open()
        deadline = self.clock() + max(0.0, float(wait_s))
        items: list[Item] = []
        if not self._running:
            self.sleep(max(0.0, deadline - self.clock()))
            return items
        period = 1.0 / self.rate_hz
        while True:
            now = self.clock()
            if self._next_due >= deadline and not (wait_s <= 0 and self._next_due <= now):
                self.sleep(max(0.0, deadline - now))
                return items
            if self._next_due > now:
                self.sleep(self._next_due - now)
            items.append(self._measure())
            self._next_due += period
            late = self.clock() - self._next_due
            if late > period:  # fell behind (slow host): resynchronise instead of bursting
                self.counters["late"] += 1
                self._next_due = self.clock()

    def _measure(self) -> Item:
        """One single measurement → a Sample, or an Event when it is rejected or lost."""
        seq = self._seq
        self._seq = (self._seq + 1) & 0xFFFF
        self.counters["measurements"] += 1
        try:
            item = self._measure_once(seq)
        except OSError as exc:
            self._bus_errors += 1
            self.counters["i2c_errors"] += 1
            if self._bus_errors >= MAX_CONSECUTIVE_BUS_ERRORS or exc.errno in (errno.ENODEV, errno.EBADF):
                raise PortUnavailable(f"{self.where.path}: the bus stopped answering ({exc})") from None
            return Event("rejected", seq=seq, count=1, detail=f"i2c error: {exc}")
        self._bus_errors = 0
        return item

    def _measure_once(self, seq: int) -> Item:
        if self._rb(AK_ADDR, self.mag.st1) & ST1_DRDY:
            # Unread data from an earlier measurement (one that finished after its deadline,
            # or someone else's): DRDY would be already set and the next burst would read the
            # new measurement mid-conversion (DERR). Read it out to clear DRDY.
            self._block(AK_ADDR, self.mag.data, self.mag.burst)
            self.counters["stale_cleared"] += 1
        t_trigger = self.clock()
        self._wb(AK_ADDR, self.mag.cntl, self._mode_bits(MODE_SINGLE))
        if not self._wait_drdy(t_trigger):
            self._drdy_misses += 1
            self.counters["drdy_timeout"] += 1
            self._ak_mode(MODE_POWER_DOWN)
            if self._drdy_misses >= MAX_CONSECUTIVE_DRDY_MISSES:
                raise DataNotReady(
                    f"{self.where.path} 0x0C: DRDY never set within {self.drdy_timeout_s * 1000:.0f} ms "
                    f"for {self._drdy_misses} measurements in a row ({self.chip.magnetometer.value} stuck or not measuring)"
                )
            return Event("rejected", seq=seq, count=1, detail="DRDY timeout")
        self._drdy_misses = 0
        burst = self._block(AK_ADDR, self.mag.data, self.mag.burst)  # HXL..HZH(, TMPS), ST2: one read
        raw, st2 = _measurement(burst)
        t_hi, t_lo = self._block(self.where.address, self.imu.temp_out_h, 2)
        temp_raw = _int16(t_lo, t_hi)
        reason = _rejection(raw, st2, self.chip)
        if reason:
            self.counters["rejected"] += 1
            self.counters[f"rejected_{reason}"] += 1
            return Event("rejected", seq=seq, count=1, detail=f"{reason}: raw={list(raw)} st2=0x{st2:02X}")
        self.counters["samples"] += 1
        field = [r * self.chip.ut_per_count * asa_gain(a) for r, a in zip(raw, self.asa)]
        return Sample(
            seq=seq,
            t_s=t_trigger,
            field_ut=(float(field[0]), float(field[1]), float(field[2])),
            raw=raw,
            st2=st2,
            temp_c=temp_raw_to_c(temp_raw, self.chip),
            chip=self.chip,
        )


    def _wait_drdy(self, t_trigger: float) -> bool:
        """Poll ST1.DRDY on the monotonic clock until ``drdy_timeout_s`` after the trigger."""
        deadline = t_trigger + self.drdy_timeout_s
        first = t_trigger + MEASURE_MIN_S
        now = self.clock()
        if first > now:
            self.sleep(first - now)
        while True:
            if self._rb(AK_ADDR, self.mag.st1) & ST1_DRDY:
                return True
            now = self.clock()
            if now >= deadline:
                return False
            self.sleep(min(DRDY_POLL_S, deadline - now))

    # -- self-test ------------------------------------------------------------------------------
    def _self_test(self) -> SelfTestResult:
        """The magnetometer's self-test: an internal field is applied (ASTC.SELF on the AK8975
        and AK8963; the AK09916's self-test mode applies it itself), one measurement in
        self-test mode, judged against this chip's datasheet window. Leaves it powered down."""
        self._require_open()
        was_running = self._running
        self._running = False
        try:
            self._ak_mode(MODE_POWER_DOWN)
            if self.mag.astc is not None:
                self._wb(AK_ADDR, self.mag.astc, ASTC_SELF)
            try:
                t0 = self.clock()
                self._ak_mode(self.mag.mode_self_test)
                if not self._wait_drdy(t0):
                    raise DataNotReady(f"{self.where.path} 0x0C: no DRDY in self-test mode within {self.drdy_timeout_s * 1000:.0f} ms")
                burst = self._block(AK_ADDR, self.mag.data, self.mag.burst)
            finally:
                if self.mag.astc is not None:
                    self._wb(AK_ADDR, self.mag.astc, 0x00)
        except OSError as exc:
            raise DeviceError(f"{self.where.path} 0x0C: self-test failed on the bus ({exc})") from None
        finally:
            if was_running:
                self._running = True
                self._next_due = self.clock()
        raw, st2 = _measurement(burst)
        result = SelfTestResult.from_registers(raw, self.asa, st2, window=self.chip.self_test_window)
        self.counters["self_test_pass" if result.passed else "self_test_fail"] += 1
        return result

    # -- closing ----------------------------------------------------------------------------------
    def _require_open(self) -> None:
        if self._closed:
            raise DeviceError(f"{self.url}: device is closed")
        if self.bus is None or self.identity is None:
            raise DeviceError(f"{self.url}: open() the device first")

    def _close_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.close()
            except OSError:
                pass

    def _close(self) -> None:
        self._running = False
        if self.bus is not None:
            try:
                self._wb(AK_ADDR, self.mag.cntl, MODE_POWER_DOWN)
            except OSError:
                pass
        self._close_bus()


def _measurement(burst) -> tuple[tuple[int, int, int], int]:
    """HXL..HZH, [TMPS,] ST2 (one burst; ST2 is its last byte) → the raw counts and ST2."""
    return (_int16(burst[0], burst[1]), _int16(burst[2], burst[3]), _int16(burst[4], burst[5])), burst[-1]


def _rejection(raw, st2: int, chip: Chip = MPU9150) -> str:
    """Why a reading is invalid ('' when it is fine): derr, hofl, rail, zero."""
    if st2 & ST2_DERR:
        return "derr"
    if st2 & ST2_HOFL:
        return "hofl"
    if any(v <= chip.count_min or v >= chip.count_max for v in raw):
        return "rail"
    if not any(raw):
        return "zero"
    return ""


def open_i2c(
    port: Port,
    dialect: Dialect = Dialect.NATIVE,
    bus_factory: Callable | None = None,
    clock: Callable[[], float] | None = None,
    sleep: Callable[[float], None] | None = None,
    store_dir=None,
    drdy_timeout_s: float = DRDY_TIMEOUT_S,
    rate_hz: int | None = None,
) -> I2CDevice:
    """Build (not yet open) the ``i2c:`` device. ``bus_factory(bus)`` returns an object with
    the smbus2.SMBus methods (default ``smbus2.SMBus``); ``clock``/``sleep`` default to the
    bus's simulated clock if it has one, else ``time.monotonic``/``time.sleep``."""
    dev = I2CDevice(port, bus_factory=bus_factory, clock=clock, sleep=sleep, store_dir=store_dir,
                    drdy_timeout_s=drdy_timeout_s)
    if rate_hz is not None:
        dev.rate_hz = check_rate(rate_hz, port.url)
    return dev
