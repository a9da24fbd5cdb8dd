"""Port strings: the one parser and the one vocabulary of options, for every backend.

    sim://[?OPTIONS]     emu://[?OPTIONS]     replay://FILE[?OPTIONS]     i2c:BUS[?OPTIONS]
    anything else        a serial port or pyserial URL, handed to pyserial untouched

An option means the same wherever it is taken; each backend takes the ones marked:

| option       | meaning                                                  | sim | emu | replay | i2c |
|--------------|----------------------------------------------------------|-----|-----|--------|-----|
| ``seed``     | physics seed: the simulated sensor and its motion        |  ✓  |  ✓  |        |     |
| ``rate``     | measurement rate, 1…100 Hz                               |  ✓  |     |        |  ✓  |
| ``pace``     | 0: as fast as read; 1: real (recorded) time; N: N× that  |  ✓  | 0/1 |   ✓    |     |
| ``eeprom``   | a file that keeps the board's EEPROM across runs         |  ✓  |  ✓  |        |     |
| ``motion``   | sphere, tilt, yaw or still                               |  ✓  |     |        |     |
| ``offset``   | hard iron x,y,z in µT                                    |  ✓  |  ✓  |        |     |
| ``noise``    | sensor noise in µT                                       |  ✓  |  ✓  |        |     |
| ``field``    | Earth field magnitude in µT                              |  ✓  |     |        |     |
| ``fault``    | ``KIND[@T][+D][=VALUE]``, repeatable (``devices.faults``) |  ✓  |  ✓  |   ✓    |     |
| ``addr``     | the MPU-9150's I2C address: 0x68 (AD0 low), 0x69 (high)  |     |  ✓  |        |  ✓  |
| ``measure_us`` | the AK8975's measurement time in µs                    |     |  ✓  |        |     |
| ``chip``     | mpu9150 (default), mpu9250 or icm20948 (``core.chips``)  |  ✓  |  ✓  |        |  ✓  |
| ``bits``     | magnetometer resolution: 14 or 16 for the mpu9250 (16)   |  ✓  |  ✓  |        |  ✓  |
| ``accel``    | on: samples carry the accelerometer (default); off: none |  ✓  |     |        |     |

On ``i2c:`` the chip is found by its ids; ``chip=`` there says which one is expected (another
is refused) and ``bits=`` picks the AK8963's resolution.

Earlier spellings still read: ``speed`` (sim://) for ``pace``, ``address`` (i2c:) for ``addr``.
Anything else — an unknown option, a malformed value, a missing file or bus — is a
``PortError`` naming the option and what it takes, before anything is opened.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable
from urllib.parse import parse_qs

from ..core.chips import CHIP_NAMES, Chip, chip_named
from ..core.errors import PortError
from ..sim.physics import Motion, Scenario, demo_scenario
from .faults import BOARD_FAULTS, LINK_FAULTS, REGISTER_FAULTS, Fault, parse_fault

MPU_ADDRS = (0x68, 0x69)
RATE_MIN_HZ, RATE_MAX_HZ = 1, 100
MOTIONS = ("sphere", "tilt", "yaw", "still")


def _number(text: str) -> float:
    x = float(text)
    if not math.isfinite(x):
        raise ValueError(f"{text!r} is not a finite number")
    return x


def _seed(text: str) -> int:
    v = int(text)
    if v < 0:
        raise ValueError("a seed is a whole number ≥ 0")
    return v


def _rate(text) -> int:
    try:
        rate = int(text)
    except (TypeError, ValueError):
        raise ValueError(f"rate {text!r} is not a whole number of Hz") from None
    if not RATE_MIN_HZ <= rate <= RATE_MAX_HZ:
        raise ValueError(f"rate {rate} Hz out of range {RATE_MIN_HZ}…{RATE_MAX_HZ} "
                         "(one AK8975 measurement takes ~8 ms)")
    return rate


def check_rate(value, where: str) -> int:
    """A measurement rate in Hz, 1…100 (``rate=`` or a rate asked for in code); ``PortError``
    naming ``where`` otherwise."""
    try:
        return _rate(value)
    except ValueError as exc:
        raise PortError(f"{where}: {exc}") from None


def _pace(text: str) -> float:
    v = _number(text or "0")
    if v < 0:
        raise ValueError("pace must be ≥ 0 (0 = as fast as read, 1 = real time)")
    return v


def _motion(text: str) -> str:
    if text not in MOTIONS:
        raise ValueError(f"motion is one of {', '.join(MOTIONS)}")
    return text


def _vector3(text: str) -> tuple[float, float, float]:
    v = tuple(_number(x) for x in text.split(","))
    if len(v) != 3:
        raise ValueError("takes three comma-separated numbers (x,y,z in µT)")
    return v  # type: ignore[return-value]


def _positive(text: str) -> float:
    v = _number(text)
    if v <= 0:
        raise ValueError("must be > 0")
    return v


def _addr(text: str) -> int:
    try:
        a = int(text, 0)
    except ValueError:
        raise ValueError(f"addr={text!r} is not a number (0x68 or 0x69)") from None
    if a not in MPU_ADDRS:
        raise ValueError(f"addr=0x{a:02X}; the MPU-9150 is at 0x68 (AD0 low) or 0x69 (AD0 high)")
    return a


def _whole(text: str) -> int:
    v = int(text)
    if v <= 0:
        raise ValueError("must be a whole number > 0")
    return v


def _chip(text: str) -> str:
    name = text.strip().lower().replace("-", "")
    if name not in CHIP_NAMES:
        raise ValueError(f"chip is one of {', '.join(CHIP_NAMES)}")
    return name


def _bits(text: str) -> int:
    try:
        bits = int(text)
    except ValueError:
        raise ValueError(f"bits={text!r} is not a whole number (13, 14 or 16)") from None
    if bits not in (13, 14, 16):
        raise ValueError("bits is 13 (mpu9150), 14 or 16 (mpu9250) or 16 (icm20948)")
    return bits


def _on_off(text: str) -> bool:
    word = text.strip().lower()
    if word not in ("on", "off"):
        raise ValueError("accel is on or off")
    return word == "on"


@dataclass(frozen=True)
class Option:
    name: str
    parse: Callable[[str], object]
    meaning: str


VOCABULARY = {o.name: o for o in (
    Option("seed", _seed, "physics seed"),
    Option("rate", _rate, "measurement rate, 1…100 Hz"),
    Option("pace", _pace, "0: as fast as read, 1: real time, N: N× real time"),
    Option("eeprom", str, "EEPROM file"),
    Option("motion", _motion, "sphere, tilt, yaw or still"),
    Option("offset", _vector3, "hard iron x,y,z in µT"),
    Option("noise", _positive, "sensor noise in µT"),
    Option("field", _positive, "Earth field in µT"),
    Option("fault", str, "KIND[@T][+D][=VALUE], repeatable"),
    Option("accel", _on_off, "on: samples carry the accelerometer, off: none"),
    Option("addr", _addr, "I2C address 0x68 or 0x69"),
    Option("measure_us", _whole, "AK8975 measurement time in µs"),
    Option("chip", _chip, "mpu9150, mpu9250 or icm20948"),
    Option("bits", _bits, "magnetometer resolution (mpu9250: 14 or 16)"),
)}


@dataclass(frozen=True)
class Scheme:
    name: str
    target: str  # "" (none), "file" or "bus": what comes between the prefix and '?'
    options: tuple[str, ...]
    faults: frozenset = frozenset()
    aliases: tuple[tuple[str, str], ...] = ()

    @property
    def prefix(self) -> str:
        """What a port string of this scheme starts with (``sim://``, ``i2c:``)."""
        return "i2c:" if self.name == "i2c" else f"{self.name}://"


SCHEMES = {s.name: s for s in (
    Scheme("sim", "", ("seed", "rate", "pace", "eeprom", "motion", "offset", "noise", "field", "fault", "chip", "bits", "accel"),
           LINK_FAULTS | BOARD_FAULTS, (("speed", "pace"),)),
    Scheme("emu", "", ("seed", "pace", "eeprom", "offset", "noise", "fault", "addr", "measure_us", "chip", "bits"),
           frozenset(REGISTER_FAULTS)),
    Scheme("replay", "file", ("pace", "fault"), LINK_FAULTS),
    Scheme("i2c", "bus", ("addr", "rate", "chip", "bits"), aliases=(("address", "addr"),)),
    Scheme("serial", "port", ()),
)}


@dataclass(frozen=True)
class Port:
    """A parsed port string: its backend (``scheme``), what it points at (``target``: a file, a
    bus, a serial port; "" for the simulators) and its options as typed values."""

    url: str
    scheme: str
    target: str = ""
    options: dict = field(default_factory=dict)
    faults: tuple[Fault, ...] = ()

    def get(self, name: str, default=None):
        return self.options.get(name, default)


def scheme_of(url: str) -> str:
    """The scheme a port string names (``SCHEMES``); anything else is a serial port."""
    return next((s.name for s in SCHEMES.values() if s.name != "serial" and url.startswith(s.prefix)), "serial")


def parse_port(url: str) -> Port:
    """The one parser of port strings (see the module docstring); ``PortError`` when it is not
    one this tool can open."""
    scheme = SCHEMES[scheme_of(url)]
    if scheme.name == "serial":
        if not url.strip():
            raise PortError("no port given (a serial port such as /dev/ttyACM0, or sim://)")
        return Port(url, "serial", url)
    rest = url[len(scheme.prefix):]
    if scheme.name == "i2c" and rest.startswith("//"):  # i2c://1 reads as i2c:1
        rest = rest[2:]
    target, _, query = rest.partition("?")
    _check_target(url, scheme, target)
    options, faults = _parse_query(url, scheme, query)
    return Port(url, scheme.name, target if scheme.target else "", options, faults)


def _check_target(url: str, scheme: Scheme, target: str) -> None:
    if scheme.target == "file" and not target:
        raise PortError(f"{url!r}: {scheme.name}:// needs a file, e.g. {scheme.name}://session.cap")
    if scheme.target == "bus" and not target:
        raise PortError(f"{url!r}: no bus given (i2c:1 for /dev/i2c-1)")
    if not scheme.target and target.strip("/"):
        raise PortError(f"{url!r}: {scheme.name}:// takes options only (e.g. {scheme.name}://?seed=3), "
                        f"not {target!r}")


def _parse_query(url: str, scheme: Scheme, query: str) -> tuple[dict, tuple[Fault, ...]]:
    aliases = dict(scheme.aliases)
    options: dict = {}
    faults: list[Fault] = []
    for given, values in parse_qs(query, keep_blank_values=True).items():
        name = aliases.get(given, given)
        if name not in scheme.options:
            known = ", ".join(scheme.options) or "none"
            raise PortError(f"{url!r}: unknown option {given!r} ({scheme.prefix} takes: {known})")
        if name == "fault":
            where = f"{url!r}: "
            faults += [parse_fault(f, scheme.faults, where) for v in values for f in v.split(";") if f]
            continue
        if len(values) > 1 or name in options:
            raise PortError(f"{url!r}: option {name!r} given more than once")
        try:
            options[name] = VOCABULARY[name].parse(values[0])
        except ValueError as exc:
            raise PortError(f"{url!r}: bad {name}={values[0]!r}: {exc}") from None
    return options, tuple(sorted(faults, key=lambda f: f.t_s))


def chip_of(port: Port) -> Chip | None:
    """The chip a port string names (``chip=``, ``bits=``); None when it names none."""
    if port.get("chip") is None and port.get("bits") is None:
        return None
    try:
        return chip_named(port.get("chip", "mpu9150"), port.get("bits"))
    except ValueError as exc:
        raise PortError(f"{port.url!r}: {exc}") from None


def scenario_of(port: Port) -> Scenario:
    """The physics a simulator's port string asks for: ``demo_scenario(seed)`` with its
    ``motion``, ``offset``, ``noise`` and ``field`` options (the chip is the backend's to put
    it on: ``chip_of``)."""
    sc = demo_scenario(port.get("seed", 1))
    if port.get("motion", "sphere") != "sphere":
        sc = replace(sc, motion=Motion(port.get("motion")))
    changes = {}
    for option, name in (("offset", "hard_iron_ut"), ("noise", "noise_ut"), ("field", "field_ut")):
        if port.get(option) is not None:
            changes[name] = port.get(option)
    return sc.with_physics(**changes) if changes else sc
