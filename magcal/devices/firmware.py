"""The firmware's sources, builds and flashing, from the sources the package carries.

``FIRMWARE_DIR`` is the packaged ``firmware/`` (``magcal.recordings.shared``): in a source
checkout the tree's own folder, built in place (``firmware/build``, ``firmware/emulator/build``,
as ``make -C firmware`` does); from an installed package the builds go to the user's cache,
``$XDG_CACHE_HOME/magcal/firmware-<digest of the sources>/``, so an upgrade builds afresh and the
installation itself is never written. The build is the firmware's own Makefile (Debian's AVR
toolchain and Arduino core); flashing is avrdude through the Uno's bootloader, or arduino-cli
when avrdude is not installed.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from ..core.errors import DeviceError, PortError
from ..recordings.shared import in_source_checkout, shared_path, user_cache_dir

FIRMWARE_DIR = shared_path("firmware")
SKETCH = "magcal_mpu9150"
ARDUINO_CORE = Path("/usr/share/arduino/hardware/arduino/avr")
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")
AVR_PACKAGES = "gcc-avr avr-libc binutils-avr arduino-core-avr"
EMULATOR_PACKAGES = "simavr libsimavr-dev"
FLASH_BAUD = 115200


def _sources_digest(folder: Path) -> str:
    """A short digest of the firmware's sources (the build folders left out)."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and "build" not in p.relative_to(folder).parts:
            h.update(str(p.relative_to(folder)).encode() + b"\0" + p.read_bytes())
    return h.hexdigest()[:12]


def _build_root() -> Path:
    if in_source_checkout(FIRMWARE_DIR):
        return FIRMWARE_DIR
    return user_cache_dir() / f"firmware-{_sources_digest(FIRMWARE_DIR)}"


BUILD_ROOT = _build_root()
BUILD_DIR = BUILD_ROOT / "build"  # the sketch's objects, ELF and HEX files
EMULATOR_BUILD_DIR = BUILD_ROOT / "emulator" / "build"  # the simavr harness and the model library


@dataclass(frozen=True)
class Image:
    """One built firmware: its ELF (what the emulator runs) and its HEX (what is flashed)."""

    elf: Path
    hex: Path


IMAGE = Image(BUILD_DIR / f"{SKETCH}.elf", BUILD_DIR / f"{SKETCH}.hex")
# the same sketch for an MPU-9250/9255 whose AK8963 runs at 14-bit output (AK8963_BITS=14)
IMAGE_AK8963_14BIT = Image(BUILD_DIR / f"{SKETCH}_ak8963_14bit.elf", BUILD_DIR / f"{SKETCH}_ak8963_14bit.hex")


def toolchain_problem(emulator: bool = False) -> str | None:
    """Why the firmware (and with ``emulator``, the simavr harness) cannot be built here, or None."""
    tools = ["make", "avr-gcc", "avr-g++", "avr-objcopy", "avr-size"] + (["cc"] if emulator else [])
    missing = [t for t in tools if shutil.which(t) is None]
    if not ARDUINO_CORE.is_dir():
        missing.append(str(ARDUINO_CORE))
    if emulator and not SIMAVR_HEADER.exists():
        missing.append(str(SIMAVR_HEADER))
    if missing:
        what = "AVR toolchain/simavr" if emulator else "AVR toolchain"
        packages = AVR_PACKAGES + (" " + EMULATOR_PACKAGES if emulator else "")
        return f"{what} missing ({', '.join(missing)}); install: {packages}"
    return None


def _make(folder: Path, build: Path, *targets: str) -> None:
    cmd = ["make", "-C", str(folder), f"BUILD={build}", *targets]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-5:]
        raise DeviceError(f"building {folder.name} failed: " + " | ".join(tail))


def build_firmware() -> tuple[Image, Image]:
    """Build (or bring up to date) both firmware images; ``DeviceError`` naming what is missing."""
    problem = toolchain_problem()
    if problem:
        raise DeviceError(f"the firmware build needs the {problem}")
    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    _make(FIRMWARE_DIR, BUILD_DIR, "all")
    return IMAGE, IMAGE_AK8963_14BIT


def build_harness() -> Path:
    """Build (or bring up to date) the simavr harness that runs the firmware ELF."""
    problem = toolchain_problem(emulator=True)
    if problem:
        raise DeviceError(f"the emulator build needs the {problem}")
    EMULATOR_BUILD_DIR.mkdir(parents=True, exist_ok=True)
    _make(FIRMWARE_DIR / "emulator", EMULATOR_BUILD_DIR, "all")
    return EMULATOR_BUILD_DIR / "magcal-emu"


def flash_command(port: str, image: Path) -> list[str]:
    """The command that writes ``image`` (a HEX file) to an Uno on ``port`` through its
    bootloader: avrdude, or arduino-cli where avrdude is not installed."""
    if not port:
        raise PortError("flashing needs --port (the board's serial device, e.g. /dev/ttyACM0)")
    if shutil.which("avrdude"):
        return ["avrdude", "-p", "m328p", "-c", "arduino", "-P", port, "-b", str(FLASH_BAUD),
                "-U", f"flash:w:{image}:i"]
    if shutil.which("arduino-cli"):
        return ["arduino-cli", "upload", "-p", port, "--fqbn", "arduino:avr:uno", "--input-file", str(image)]
    raise DeviceError("flashing needs avrdude (install: avrdude) or arduino-cli")


def flash(port: str, image: Path) -> None:
    """Write ``image`` to the board on ``port``; ``DeviceError`` with the tool's last words."""
    cmd = flash_command(port, image)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        tail = [ln for ln in (r.stderr or r.stdout).splitlines() if ln.strip()][-3:]
        raise DeviceError(f"flashing {port} with {cmd[0]} failed: " + " | ".join(tail))
