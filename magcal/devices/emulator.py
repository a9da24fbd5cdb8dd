"""``emu://`` — the real firmware ELF running under simavr, spoken to through a pty.

The harness (``firmware/emulator/magcal-emu``) runs the very binary a user flashes, answers its
TWI bus with the C register model, and asks this module for every magnetometer measurement:
it prints ``M <t_us> <k>`` and a thread here answers with ``Scenario.measure(t_s, k)`` — the one
physics simulator — so tests know the truth. The host then talks to the board with its real
serial client (``ProtocolDevice`` over a pyserial port on the pty).

Options (the port string's, ``magcal.devices.port``): ``seed`` (physics seed, default 1),
``eeprom`` (EEPROM file, kept across runs; default one per seed and address in the user's state
directory, ``$XDG_STATE_HOME/magcal/emu/`` or ``~/.local/state/magcal/emu/``, so a calibration
written in one run is there in the next, as on a board; ``eeprom=none`` for a throwaway one), ``pace=1`` (simulated time follows the wall clock; 0, the default, runs as fast as it
can), ``offset``, ``noise``, ``fault`` (the register model's flags by name: ``stuck_drdy`` …),
``measure_us`` (the magnetometer's measurement time), ``addr`` (the IMU's I2C address: 0x68, AD0
low, or 0x69, AD0 high), ``chip`` (the board's chip: ``mpu9150``, the default, with its AK8975;
``mpu9250``, an AK8963; ``icm20948``, an AK09916) and ``bits`` (the AK8963's output resolution:
16, the default, or 14 — the firmware built for 14-bit output runs then). Keyword options:
``scenario=`` (a ``Scenario``, overrides the port string's physics), ``asa=(x, y, z)``,
``chip=``, ``bits=``, ``baud``. Closing the device stops the harness; opening it again starts it
again on the same EEPROM file.

The physics answers in the chip's own counts: its quantum (0.3 µT AK8975, 0.6 or 0.15 µT AK8963,
0.15 µT AK09916, each times the ASA gain where the part has one; the AK09916 has none: ASA 128),
its range and overflow, and its die-temperature register: ``Scenario.measure`` with the physics
on this chip (``Physics.chip``, the one chip table), as the simulators read.

Nothing is built implicitly unless the build is missing: then the firmware and the harness are
built once from the packaged sources (``magcal.devices.firmware``: in place in a source checkout,
else in the user's cache, so ``emu://`` works from an installed package), and a missing toolchain
is a clear ``DeviceError``.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from ..core.chips import MPU9150, Chip, chip_named
from ..core.errors import DeviceError, PortError, PortUnavailable
from ..recordings.state import board_eeprom, chip_suffix
from ..core.sample import asa_gain
from ..sim.physics import Scenario
from ..wire.dialect import Dialect
from . import firmware
from .faults import register_flags
from .port import Port, scenario_of
from .simboard import accel_counts
from .transport import WrappedTransport

FIRMWARE_DIR = firmware.FIRMWARE_DIR  # the packaged sources (the tree's own in a checkout)
ELF = firmware.IMAGE.elf
ELF_AK8963_14BIT = firmware.IMAGE_AK8963_14BIT.elf  # AK8963_BITS=14
HARNESS = firmware.EMULATOR_BUILD_DIR / "magcal-emu"
ARDUINO_CORE = Path("/usr/share/arduino/hardware/arduino/avr")
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")
AVR_PACKAGES = "gcc-avr avr-libc binutils-avr arduino-core-avr simavr libsimavr-dev"
_build_lock = threading.Lock()


@dataclass(frozen=True)
class EmuChip:
    """The emulated board's magnetometer: one row of the chip table (``magcal.core.chips``),
    whose counts, range, overflow and die temperature the physics reads in. The
    healthy coil of the physics (``Physics.self_test_counts``, an AK8975's reading) is placed at
    the same point of this chip's window, so a dead or weak coil stays outside it."""

    part: Chip

    @property
    def name(self) -> str:  # the harness's --chip
        return self.part.name

    @property
    def bits(self) -> int:
        return self.part.bits

    @property
    def has_asa(self) -> bool:
        return self.part.has_asa


    def self_test_raw(self, adjusted_ak8975, asa) -> list[int]:
        """The data registers in self-test mode for a coil that reads ``adjusted_ak8975`` on an
        AK8975: the same point of this chip's window, ASA undone (truncated, as the register)."""
        p, out = self.part, []
        for v, (lo, hi), (lo2, hi2), a in zip(adjusted_ak8975, MPU9150.self_test_window, p.self_test_window, asa):
            adjusted = lo2 + (v - lo) * (hi2 - lo2) / (hi - lo)
            out.append(int(max(p.count_min, min(p.count_max, int(adjusted / asa_gain(a))))))
        return out


def emu_chip(chip: str | None = None, bits=None) -> EmuChip:
    """The chip an ``emu://`` board carries (``chip``, ``bits`` as the port string gives them);
    ``PortError`` naming what is possible otherwise."""
    name = str(getattr(chip, "value", chip) or "mpu9150").lower()
    try:
        want = None if bits is None else int(bits)
    except (TypeError, ValueError):
        raise PortError(f"bits={bits!r} is not a whole number") from None
    try:
        return EmuChip(chip_named(name, want))
    except ValueError as exc:
        raise PortError(f"emu://: {exc}") from None


def toolchain_problem() -> str | None:
    """Why the emulated board cannot be built here, or None when it can."""
    missing = []
    for tool in ("make", "cc", "avr-gcc", "avr-g++", "avr-objcopy", "avr-size"):
        if shutil.which(tool) is None:
            missing.append(tool)
    if not ARDUINO_CORE.is_dir():
        missing.append(str(ARDUINO_CORE))
    if not SIMAVR_HEADER.exists():
        missing.append(str(SIMAVR_HEADER))
    if missing:
        return f"AVR toolchain/simavr missing ({', '.join(missing)}); install: {AVR_PACKAGES}"
    return None


def ensure_built() -> tuple[Path, Path]:
    """The firmware ELF and the harness, built first if either is missing."""
    with _build_lock:
        if ELF.exists() and ELF_AK8963_14BIT.exists() and HARNESS.exists():
            return ELF, HARNESS
        problem = toolchain_problem()
        if problem:
            raise DeviceError(f"emu:// needs the firmware build: {problem}")
        try:
            firmware.build_firmware()
            firmware.build_harness()
        except DeviceError as exc:
            raise DeviceError(f"emu://: {exc}") from None
        return ELF, HARNESS


class EmulatedBoard:
    """One run of the harness: the simulated Uno + its IMU and magnetometer (``chip``, an
    ``EmuChip``), its pty and its EEPROM file.

    ``scenario`` is the truth the field comes from; ``served`` keeps the last measurements
    handed to the board as ``(t_s, k, (hx, hy, hz), st2, temp_raw)``."""

    def __init__(
        self,
        scenario: Scenario,
        eeprom_path: str | os.PathLike | None = None,
        *,
        pace: bool = False,
        faults: int = 0,
        measure_us: int | None = None,
        boot_delay_ms: int = 100,
        mpu_addr: int = 0x68,
        chip: EmuChip | None = None,
    ):
        self.chip = chip or emu_chip()
        if scenario.physics.chip != self.chip.part:  # the physics reads in this chip's counts
            scenario = scenario.with_physics(chip=self.chip.part)  # (no fuse ROM: ASA 128, a factor of 1)
        self.scenario = scenario
        self._tmpdir = None  # removed when the board is dropped: its EEPROM lives across restarts
        if eeprom_path is None:
            self._tmpdir = tempfile.TemporaryDirectory(prefix="magcal-emu-")
            eeprom_path = os.path.join(self._tmpdir.name, "eeprom.bin")
        self.eeprom_path = str(eeprom_path)
        self.pace = pace
        self.faults = int(faults)
        self.measure_us = measure_us
        self.boot_delay_ms = boot_delay_ms
        self.mpu_addr = int(mpu_addr)
        self.served: deque = deque(maxlen=200_000)
        self.pty: str | None = None
        self._proc: subprocess.Popen | None = None
        self._thread: threading.Thread | None = None
        self._error: str | None = None

    def start(self) -> str:
        """Start the harness; returns the pty path. The AVR boots when a host opens it."""
        elf, harness = ensure_built()
        if self.chip.bits == 14:
            elf = ELF_AK8963_14BIT
        asa = self.scenario.physics.asa
        cmd = [str(harness), "--chip", self.chip.name, "--eeprom", self.eeprom_path,
               "--asa", ",".join(str(int(a)) for a in asa),
               "--faults", str(self.faults), "--boot-delay-ms", str(self.boot_delay_ms),
               "--addr", f"0x{self.mpu_addr:02x}",
               "--self-test", ",".join(str(v) for v in self._self_test_raw())]
        if self.measure_us is not None:
            cmd += ["--measure-us", str(int(self.measure_us))]
        if self.pace:
            cmd.append("--pace")
        cmd.append(str(elf))
        try:
            self._proc = subprocess.Popen(
                cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                text=True, bufsize=1,
            )
        except OSError as exc:
            raise DeviceError(f"emu://: cannot start the harness: {exc}") from exc
        line = self._proc.stdout.readline()
        if not line.startswith("PTY "):
            err = self._proc.stderr.read() if self._proc.poll() is not None else ""
            self.stop()
            raise DeviceError(f"emu://: the harness did not report its pty ({line.strip()!r} {err.strip()})")
        self.pty = line.split(None, 1)[1].strip()
        self._thread = threading.Thread(target=self._serve, name="magcal-emu-physics", daemon=True)
        self._thread.start()
        return self.pty

    def _self_test_raw(self) -> list[int]:
        ph = self.scenario.physics
        if self.chip.bits == 13:
            return list(ph.self_test_raw())
        return self.chip.self_test_raw(ph.self_test_counts, ph.asa)

    def measure(self, t_s: float, k: int) -> tuple[tuple[int, int, int], int, int]:
        """The chip's data registers, ST2 (HOFL) and TEMP_OUT for measurement k at t_s."""
        raw, st2, temp = self.scenario.measure([t_s], [k])  # the physics on this chip (its counts, rails, HOFL, TEMP_OUT)
        return tuple(int(v) for v in raw[0]), int(st2[0]), int(temp[0])

    def accel(self, t_s: float, k: int) -> tuple[int, int, int]:
        """The accelerometer's ACCEL_*OUT registers (±2 g counts, the IMU's axes) for measurement k at t_s."""
        return tuple(int(v) for v in accel_counts(self.scenario.accel_body_g([t_s], [k]), self.chip.part)[0])

    def _answer(self, parts: list[str]) -> str:
        """``M t_us k [bits]`` → ``hx hy hz hofl temp ax ay az``; the firmware's resolution must be the
        board's (a mismatch would rescale every sample)."""
        if len(parts) == 4 and int(parts[3]) != self.chip.bits:
            raise DeviceError(f"emu://: the firmware runs the magnetometer at {parts[3]}-bit output, "
                              f"the board was asked for {self.chip.bits}-bit")
        t_s, k = int(parts[1]) / 1e6, int(parts[2])
        (hx, hy, hz), s2, tr = self.measure(t_s, k)
        self.served.append((t_s, k, (hx, hy, hz), s2, tr))
        ax, ay, az = self.accel(t_s, k)
        return f"{hx} {hy} {hz} {1 if s2 & 0x08 else 0} {tr} {ax} {ay} {az}\n"

    def _serve(self) -> None:
        """Answer every ``M t_us k [bits]`` with the physics' measurement at (t, k)."""
        proc = self._proc
        try:
            for line in proc.stdout:
                parts = line.split()
                if len(parts) not in (3, 4) or parts[0] != "M":
                    continue
                proc.stdin.write(self._answer(parts))
                proc.stdin.flush()
        except (OSError, ValueError) as exc:  # harness gone: the reader side reports it
            self._error = str(exc)
        except Exception as exc:  # the physics failed: stop the board rather than hang it
            self._error = f"physics provider failed: {exc!r}"
            try:
                proc.stdin.close()
            except (OSError, ValueError):
                pass

    def reset(self) -> None:
        """Reset the AVR now (like pressing the reset button); the host sees a fresh hello."""
        if self._proc is None or self._proc.poll() is not None:
            raise DeviceError("emu://: the emulated board is not running")
        self._proc.send_signal(signal.SIGUSR1)

    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self) -> None:
        """Stop the harness (it saves the EEPROM file first)."""
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            for f in (proc.stdin, proc.stdout, proc.stderr):
                try:
                    f.close()
                except (OSError, ValueError):
                    pass
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None


class _HarnessPort(WrappedTransport):
    """The pty of a running harness: closing it stops the harness (it saves the EEPROM)."""

    def __init__(self, inner, board: EmulatedBoard):
        super().__init__(inner)
        self.board = board

    def close(self) -> None:
        try:
            self.inner.close()
        finally:
            self.board.stop()


def _harness_connector(board: EmulatedBoard, baud: int):
    def connect():
        import serial  # pyserial

        pty = board.start()
        try:
            return _HarnessPort(serial.Serial(pty, baudrate=int(baud), timeout=0.05), board)
        except (serial.SerialException, OSError) as exc:
            board.stop()
            raise PortUnavailable(f"emu://: cannot open the pty {pty}: {exc}") from exc

    return connect


def eeprom_of(port: Port, chip: EmuChip | None = None) -> str | None:
    """The EEPROM file an ``emu://`` port keeps: ``eeprom=PATH``; by default one per seed,
    address and chip in the user's state directory; None (a throwaway file) for ``eeprom=none``."""
    name = f"eeprom-seed{port.get('seed', 1)}-{port.get('addr', 0x68):#04x}{chip_suffix(chip)}.bin"
    return board_eeprom(port.get("eeprom"), "emu", name)


def open_emulated(port: Port, dialect: Dialect = Dialect.NATIVE, *, scenario: Scenario | None = None, asa=None,
                  chip: str | None = None, bits: int | None = None, baud: int = 115200, tap=None,
                  reply_timeout_s: float = 1.5, boot_timeout_s: float = 3.0):
    """``emu://[?seed=N&chip=icm20948&eeprom=PATH&pace=1…]`` → the v1 protocol client on the
    emulated board (``chip``/``bits`` given here override the port string's).

    The returned device has ``.board`` (the ``EmulatedBoard``: its ``scenario``, ``reset()``,
    ``eeprom_path``, ``served``). The harness starts when the device is opened."""
    from .protocol_client import ProtocolDevice

    if port.get("pace", 0) not in (0, 1):
        raise PortError(f"{port.url!r}: emu:// paces at 0 (as fast as it runs) or 1 (real time), "
                        f"not {port.get('pace'):g}")
    scenario = scenario or scenario_of(port)
    if asa is not None:
        scenario = scenario.with_physics(asa=tuple(int(a) for a in asa))
    board_chip = emu_chip(chip or port.get("chip"), bits if bits is not None else port.get("bits"))
    board = EmulatedBoard(scenario, eeprom_of(port, board_chip), pace=port.get("pace", 0) == 1,
                          faults=register_flags(port.faults), measure_us=port.get("measure_us"),
                          mpu_addr=port.get("addr", 0x68), chip=board_chip)
    ensure_built()  # a missing toolchain is named now, not at the first connection
    dev = ProtocolDevice(port.url, _harness_connector(board, baud), transport_name="emu", tap=tap,
                         reply_timeout_s=reply_timeout_s, boot_timeout_s=boot_timeout_s)
    dev.board = board
    return dev
