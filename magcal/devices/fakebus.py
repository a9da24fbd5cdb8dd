"""A behavioural fake I2C bus that stands in for ``smbus2.SMBus`` in tests and demos.

It is not a second register model: every byte goes through the one C model
(``firmware/emulator/mpu9150_model.c``, loaded with ctypes from
``firmware/emulator/build/libmpu9150model.so``, or from an installed package the user's cache:
``magcal.devices.firmware``; built with ``make``/``cc`` when missing or stale), whose field comes from the one physics simulator (``Scenario.measure``). So the bypass
gating, DRDY after the measurement delay, DERR, HOFL and clamping, fuse-ROM-only ASA and the
burst wrap are exactly what the simavr-emulated Arduino sees.

Time is simulated: ``FakeBus.clock`` is a ``FakeClock`` (call it for seconds; ``sleep(dt)``
advances it), and every bus transfer also advances it by its duration on the wire (9 bit
times per byte at ``bus_hz``), so a backend that polls without sleeping still sees time pass.
A NACK raises ``OSError(121, ...)`` like the Linux driver (EREMOTEIO).

    bus = FakeBus(demo_scenario(3))
    dev = open_i2c("i2c:1", bus_factory=lambda n: bus)   # uses bus.clock automatically
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import subprocess
import tempfile
import threading
from collections import Counter, deque
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.chips import DEFAULT, Chip, Magnetometer, chip_named
from ..core.errors import DeviceError
from ..core.sample import ST2_HOFL
from ..sim.physics import Scenario, demo_scenario
from . import firmware
from .simboard import accel_counts

EMULATOR_DIR = firmware.FIRMWARE_DIR / "emulator"  # the packaged sources (magcal.devices.firmware)
LIB_NAME = "libmpu9150model.so"
ENV_LIB = "MAGCAL_MODEL_LIB"
BLOCK_MAX = 32  # smbus2's I2C_SMBUS_BLOCK_MAX
I2C_M_RD = 0x0001

# the register model's chip numbers (MPU_CHIP_* in mpu9150_model.h)
MODEL_CHIP = {"mpu9150": 0, "mpu9250": 1, "icm20948": 3}

FAULTS = {  # names for the model's fault flags (mpu9150_model.h)
    "wrong_whoami": 1 << 0,
    "no_ak": 1 << 1,
    "stuck_drdy": 1 << 2,
    "wrong_wia": 1 << 3,
}


class _Measurement(ctypes.Structure):
    _fields_ = [
        ("hx", ctypes.c_int16),
        ("hy", ctypes.c_int16),
        ("hz", ctypes.c_int16),
        ("hofl", ctypes.c_uint8),
        ("temp_raw", ctypes.c_int16),
        ("ax", ctypes.c_int16),
        ("ay", ctypes.c_int16),
        ("az", ctypes.c_int16),
    ]


_PROVIDER = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint64, ctypes.POINTER(_Measurement))

_lib = None
_lib_lock = threading.Lock()


def _stale(lib: Path) -> bool:
    if not lib.exists():
        return True
    sources = [p for p in EMULATOR_DIR.glob("mpu9150_model.[ch]")]
    return any(p.stat().st_mtime > lib.stat().st_mtime for p in sources)


def _build(lib: Path) -> None:
    source = EMULATOR_DIR / "mpu9150_model.c"
    if not source.exists():
        raise DeviceError(f"the register model source {source} is missing; the fake I2C bus needs it")
    if shutil.which("make"):
        proc = subprocess.run(["make", "-s", "-C", str(EMULATOR_DIR), f"BUILD={lib.parent}", "lib"], capture_output=True, text=True)
        if proc.returncode == 0 and lib.exists():
            return
        detail = (proc.stderr or proc.stdout).strip()
    else:
        detail = "make not found"
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if not cc:
        raise DeviceError(
            f"cannot build {lib.name} for the fake I2C bus: no C compiler (install gcc or set CC); {detail}"
        )
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as scratch:  # a fresh name nobody can plant a link at
        tmp = os.path.join(scratch, lib.name)
        proc = subprocess.run(
            [cc, "-O2", "-std=gnu99", "-shared", "-fPIC", "-o", tmp, str(source)],
            capture_output=True,
            text=True,
        )
        if proc.returncode != 0:
            raise DeviceError(f"building {lib.name} failed: {(proc.stderr or proc.stdout).strip()}")
        os.replace(tmp, lib)


def load_model_library() -> ctypes.CDLL:
    """The register model as a shared library (built on first use when missing or stale)."""
    global _lib
    with _lib_lock:
        if _lib is not None:
            return _lib
        env = os.environ.get(ENV_LIB)
        if env:
            path = Path(env)
            if not path.exists():
                raise DeviceError(f"${ENV_LIB} names {path}, which does not exist")
        else:
            path = firmware.EMULATOR_BUILD_DIR / LIB_NAME
            if _stale(path):
                _build(path)
        lib = ctypes.CDLL(str(path))
        lib.mpu_model_size.restype = ctypes.c_size_t
        lib.mpu_model_size.argtypes = []
        lib.mpu_model_init.restype = None
        lib.mpu_model_init.argtypes = [ctypes.c_void_p, ctypes.c_uint8, ctypes.POINTER(ctypes.c_uint8), _PROVIDER, ctypes.c_void_p]
        lib.mpu_model_set_faults.restype = None
        lib.mpu_model_set_faults.argtypes = [ctypes.c_void_p, ctypes.c_uint]
        lib.mpu_model_set_measure_us.restype = None
        lib.mpu_model_set_measure_us.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
        lib.mpu_model_set_self_test.restype = None
        lib.mpu_model_set_self_test.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int16)]
        lib.mpu_model_start.restype = ctypes.c_int
        lib.mpu_model_start.argtypes = [ctypes.c_void_p, ctypes.c_uint8, ctypes.c_int, ctypes.c_uint64]
        lib.mpu_model_write.restype = ctypes.c_int
        lib.mpu_model_write.argtypes = [ctypes.c_void_p, ctypes.c_uint8, ctypes.c_uint64]
        lib.mpu_model_read.restype = ctypes.c_int
        lib.mpu_model_read.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint64]
        lib.mpu_model_stop.restype = None
        lib.mpu_model_stop.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
        lib.mpu_model_set_chip.restype = ctypes.c_int
        lib.mpu_model_set_chip.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.mpu_model_mag_bits.restype = ctypes.c_int
        lib.mpu_model_mag_bits.argtypes = [ctypes.c_void_p]
        lib.mpu_model_peek.restype = ctypes.c_uint8
        lib.mpu_model_peek.argtypes = [ctypes.c_void_p, ctypes.c_uint8, ctypes.c_uint8]
        _lib = lib
        return lib


class FakeClock:
    """Simulated monotonic time in seconds: ``clock()`` reads it, ``clock.sleep(dt)`` advances it."""

    def __init__(self, start_s: float = 0.0):
        self.t_s = float(start_s)

    def __call__(self) -> float:
        return self.t_s

    def sleep(self, dt_s: float) -> None:
        if dt_s < 0:
            raise ValueError(f"cannot sleep a negative time ({dt_s} s)")
        self.t_s += float(dt_s)

    advance = sleep


def _nack(addr: int, what: str) -> OSError:
    return OSError(errno.EREMOTEIO, f"Remote I/O error (NACK from 0x{addr:02X} on {what})")


class FakeBus:
    """The ``smbus2.SMBus`` methods the i2c backend uses, as byte-level transactions on the model.

    ``scenario``: the physics behind the AK8975 (default ``demo_scenario(1)``); its ASA bytes
    are the fuse ROM. ``address``: 0x68 or 0x69 (AD0). ``faults``: names from ``FAULTS`` or the
    model's bit flags. ``clock``: a ``FakeClock`` or any callable returning seconds (then bus
    transfers do not advance it). ``measure_us``: the magnetometer's measurement time.
    ``chip``: the part on the bus (a :mod:`magcal.core.chips` row; default the MPU-9150); the
    scenario's physics is put on it, and each measurement is answered in the counts of the
    resolution the host set (the AK8963's CNTL1 BIT picks 14 or 16 bits).
    """

    def __init__(
        self,
        scenario: Scenario | None = None,
        address: int = 0x68,
        faults=0,
        clock: Callable[[], float] | None = None,
        measure_us: int = 7300,
        bus_hz: float = 400_000.0,
        chip: Chip = DEFAULT,
    ):
        scenario = scenario if scenario is not None else demo_scenario(1)
        self.chip = chip
        self.scenario = scenario if scenario.physics.chip == chip else scenario.on_chip(chip)
        self._by_bits = {chip.bits: self.scenario}
        self.address = address
        self.clock = clock if clock is not None else FakeClock()
        self.bus_hz = float(bus_hz)
        self.measurements = 0  # k: how many measurements the provider has served
        self.measurement_times_s: list[float] = []
        self.counts: Counter = Counter()  # transactions, nacks, bytes
        self.transactions: deque = deque(maxlen=4096)  # (kind, addr, first byte written, n read)
        self._closed = False
        self._provider_error: BaseException | None = None
        self._lib = load_model_library()
        self._mem = ctypes.create_string_buffer(self._lib.mpu_model_size())
        self._provider = _PROVIDER(self._provide)  # keep a reference: C holds the pointer
        asa = (ctypes.c_uint8 * 3)(*[int(a) for a in self.scenario.physics.asa])
        self._lib.mpu_model_init(self._mem, address, asa, self._provider, None)
        if self._lib.mpu_model_set_chip(self._mem, MODEL_CHIP[chip.name]) != 0:
            raise DeviceError(f"the register model does not know chip {chip.name}")
        self._lib.mpu_model_set_measure_us(self._mem, int(measure_us))
        self._lib.mpu_model_set_self_test(self._mem, (ctypes.c_int16 * 3)(*self.scenario.physics.self_test_raw()))
        self.set_faults(faults)

    # -- configuration ---------------------------------------------------------------------
    def set_faults(self, faults) -> None:
        if isinstance(faults, str):
            faults = [faults] if faults else []
        if not isinstance(faults, int):
            bits = 0
            for name in faults:
                if name not in FAULTS:
                    raise ValueError(f"unknown fault {name!r} ({', '.join(FAULTS)})")
                bits |= FAULTS[name]
            faults = bits
        self._lib.mpu_model_set_faults(self._mem, int(faults))

    def peek(self, addr: int, reg: int) -> int:
        """A register's value without side effects (for tests)."""
        return int(self._lib.mpu_model_peek(self._mem, addr, reg))

    @property
    def truth(self):
        return self.scenario.physics.truth()

    # -- the provider: the physics answers each completed measurement ------------------------
    def _provide(self, _ctx, t_us, out) -> int:
        try:
            t_s = t_us / 1e6
            k = self.measurements
            scenario = self._at_bits(int(self._lib.mpu_model_mag_bits(self._mem)))
            raw, st2, temp_raw = scenario.measure(np.array([t_s]), np.array([k]))
            m = out.contents
            m.hx, m.hy, m.hz = (int(v) for v in raw[0])
            m.hofl = 1 if int(st2[0]) & ST2_HOFL else 0
            m.temp_raw = int(np.clip(temp_raw[0], -32768, 32767))
            m.ax, m.ay, m.az = (int(v) for v in accel_counts(scenario.accel_body_g([t_s], [k]), self.chip)[0])
            self.measurements += 1
            self.measurement_times_s.append(t_s)
            return 0
        except BaseException as exc:  # never let an exception cross the C boundary
            self._provider_error = exc
            return -1

    def _at_bits(self, bits: int) -> Scenario:
        """The scenario whose chip reads at ``bits`` (the AK8963 switches with CNTL1 BIT)."""
        if bits not in self._by_bits:
            if self.chip.magnetometer is not Magnetometer.AK8963:
                raise DeviceError(f"{self.chip.label} has no {bits}-bit output")
            row = chip_named(self.chip.name, bits)
            self._by_bits[bits] = self.scenario.with_physics(chip=row)
        return self._by_bits[bits]

    # -- byte-level transactions ---------------------------------------------------------------
    def _t_us(self) -> int:
        return int(round(self.clock() * 1e6))

    def _tick(self, nbytes: int) -> None:
        sleep = getattr(self.clock, "sleep", None)
        if sleep is not None and self.bus_hz > 0:
            sleep(nbytes * 9.0 / self.bus_hz)

    def _check(self) -> None:
        if self._closed:
            raise OSError(errno.EBADF, "Bad file descriptor (bus closed)")
        err, self._provider_error = self._provider_error, None
        if err is not None:
            raise RuntimeError("the physics provider failed inside the register model") from err

    def _start(self, addr: int, is_read: bool) -> None:
        self._tick(1)
        if self._lib.mpu_model_start(self._mem, addr, 1 if is_read else 0, self._t_us()) != 0:
            self._stop()
            self.counts["nacks"] += 1
            raise _nack(addr, "address")

    def _write(self, addr: int, byte: int) -> None:
        self._tick(1)
        if self._lib.mpu_model_write(self._mem, int(byte) & 0xFF, self._t_us()) != 0:
            self._stop()
            self.counts["nacks"] += 1
            raise _nack(addr, "data")

    def _read(self, addr: int) -> int:
        self._tick(1)
        b = ctypes.c_uint8()
        if self._lib.mpu_model_read(self._mem, ctypes.byref(b), self._t_us()) != 0:
            self._stop()
            self.counts["nacks"] += 1
            raise _nack(addr, "read")
        return int(b.value)

    def _stop(self) -> None:
        self._lib.mpu_model_stop(self._mem, self._t_us())

    def _transfer(self, addr: int, out: bytes | list[int], n_in: int) -> list[int]:
        """START addr+W, bytes out, [repeated START addr+R, n_in bytes in], STOP."""
        self._check()
        self.counts["transactions"] += 1
        self.transactions.append(("rw" if n_in else "w", addr, out[0] if out else None, n_in))
        data: list[int] = []
        if out or not n_in:
            self._start(addr, False)
            for b in out:
                self._write(addr, b)
        if n_in:
            self._start(addr, True)
            data = [self._read(addr) for _ in range(n_in)]
        self._stop()
        self._check()
        return data

    # -- the smbus2.SMBus surface -----------------------------------------------------------------
    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        return self._transfer(i2c_addr, [register], 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        self._transfer(i2c_addr, [register, value], 0)

    def read_byte(self, i2c_addr: int, force=None) -> int:
        self._check()
        self._start(i2c_addr, True)
        b = self._read(i2c_addr)
        self._stop()
        return b

    def write_byte(self, i2c_addr: int, value: int, force=None) -> None:
        self._transfer(i2c_addr, [value], 0)

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None) -> list[int]:
        if length > BLOCK_MAX:
            raise ValueError(f"Desired block length over {BLOCK_MAX} bytes")
        return self._transfer(i2c_addr, [register], length)

    def write_i2c_block_data(self, i2c_addr: int, register: int, data, force=None) -> None:
        if len(data) > BLOCK_MAX:
            raise ValueError(f"Data length cannot exceed {BLOCK_MAX} bytes")
        self._transfer(i2c_addr, [register, *data], 0)

    def i2c_rdwr(self, *i2c_msgs) -> None:
        """Combined transfer (smbus2.i2c_msg): repeated starts, one STOP at the end."""
        self._check()
        self.counts["transactions"] += 1
        try:
            for msg in i2c_msgs:
                addr, n = int(msg.addr), int(msg.len)
                if msg.flags & I2C_M_RD:
                    self._start(addr, True)
                    data = bytes(self._read(addr) for _ in range(n))
                    ctypes.memmove(msg.buf, data, n)
                else:
                    self._start(addr, False)
                    for b in bytes(msg):
                        self._write(addr, b)
        finally:
            self._stop()
        self._check()

    def close(self) -> None:
        self._closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
