"""Device backends, chosen by a port string. This table is the table of contents.

| port string                      | backend                                              |
|----------------------------------|------------------------------------------------------|
| ``sim://[?seed=N&eeprom=FILE…]`` | pure-Python simulated board speaking protocol v1     |
| ``emu://[?seed=N&eeprom=FILE…]`` | the real firmware ELF under simavr, through a pty    |
| ``replay://FILE[?pace=1]``       | a recorded capture, byte-exact                       |
| ``i2c:BUS[?addr=0x69]``          | the chip straight on a Linux I2C bus (smbus2)        |
| anything else                    | a serial port or pyserial URL (``/dev/ttyACM0``,     |
|                                  | ``COM3``, ``socket://``, ``rfc2217://``, ``loop://``) |

``dialect="motioncal"`` on a serial port speaks the PJRC/Adafruit ``Raw:`` convention instead;
``dialect="auto"`` listens first and picks. The options of every port string are one vocabulary
with one error (``magcal.devices.port``); keyword options a backend does not take are refused
the same way. Backends are imported lazily, so a missing optional dependency only matters when
used.
"""

from __future__ import annotations

import importlib
import inspect

from ..core.errors import DeviceError, PortError
from ..wire.dialect import Dialect
from .base import Abilities, Device, Event, Identity, Item
from .port import Port, parse_port, scheme_of

# backend → "module:factory"; each factory is called as factory(port, dialect=…, **options) → Device
BACKENDS = {
    "sim": "magcal.devices.simboard:open_sim",
    "emu": "magcal.devices.emulator:open_emulated",
    "replay": "magcal.devices.replay:open_replay",
    "i2c": "magcal.devices.i2c:open_i2c",
    "serial": "magcal.devices.protocol_client:open_serial",
    "motioncal": "magcal.devices.motioncal_client:open_motioncal",
}


def backend_of(port: Port, dialect: Dialect) -> str:
    """Which backend serves ``port`` in ``dialect`` (a replay follows its capture's header)."""
    if dialect is Dialect.MOTIONCAL and port.scheme not in ("serial", "replay"):
        raise PortError(f"--dialect motioncal needs a serial port or a replay://, not {port.url!r}")
    return "motioncal" if dialect is Dialect.MOTIONCAL and port.scheme == "serial" else port.scheme


def open_device(url: str, dialect: Dialect | str = Dialect.NATIVE, **options) -> Device:
    """Build (not yet open) the device a port string names; ``PortError`` when the string, the
    dialect or an option is not one its backend takes."""
    port = parse_port(url)
    try:
        dialect = Dialect.named(dialect)
    except ValueError as exc:
        raise PortError(str(exc)) from None
    backend = backend_of(port, dialect)
    module, _, name = BACKENDS[backend].partition(":")
    try:
        factory = getattr(importlib.import_module(module), name)
    except ImportError as exc:
        raise DeviceError(f"backend for {url!r} is unavailable: {exc}") from exc
    try:
        inspect.signature(factory).bind(port, dialect=dialect, **options)
    except TypeError:
        taken = set(inspect.signature(factory).parameters)
        unknown = ", ".join(sorted(set(options) - taken))
        raise PortError(f"{url!r}: the {backend} backend takes no option {unknown}") from None
    return factory(port, dialect=dialect, **options)


__all__ = ["Abilities", "Device", "Dialect", "Event", "Identity", "Item", "Port", "open_device", "parse_port", "scheme_of"]
