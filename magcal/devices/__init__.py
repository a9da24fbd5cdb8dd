"""Device backends, chosen by a URL-like string. This table is the table of contents.

| port string                      | backend                                              |
|----------------------------------|------------------------------------------------------|
| ``sim://[?seed=N&eeprom=FILE…]`` | pure-Python simulated board speaking protocol v1     |
| ``emu://[?seed=N&eeprom=FILE…]`` | the real firmware ELF under simavr, through a pty    |
| ``replay://FILE[?pace=1]``       | a recorded capture, byte-exact                       |
| ``i2c:BUS[?addr=0x69]``          | the chip straight on a Linux I2C bus (smbus2)        |
| anything else                    | a serial port or pyserial URL (``/dev/ttyACM0``,     |
|                                  | ``COM3``, ``socket://``, ``rfc2217://``, ``loop://``) |

``dialect="motioncal"`` on a serial port speaks the PJRC/Adafruit ``Raw:`` convention instead.
Backends are imported lazily, so a missing optional dependency only matters when used.
"""

from __future__ import annotations

import importlib

from ..core.errors import DeviceError
from .base import Device, Event, Identity, Item

# scheme → "module:factory"; each factory is called as factory(url, **options) → Device
_REGISTRY = {
    "sim": "magcal.devices.simboard:open_sim",
    "emu": "magcal.devices.emulator:open_emulated",
    "replay": "magcal.devices.replay:open_replay",
    "i2c": "magcal.devices.i2c:open_i2c",
    "serial": "magcal.devices.link:open_serial",
    "motioncal": "magcal.devices.motioncal:open_motioncal",
}


def scheme_of(url: str) -> str:
    """The backend a port string selects (see the table above)."""
    if url.startswith("i2c:"):
        return "i2c"
    for scheme in ("sim", "emu", "replay"):
        if url.startswith(scheme + "://"):
            return scheme
    return "serial"


def open_device(url: str, dialect: str = "native", **options) -> Device:
    """Build (not yet open) the device a port string names."""
    scheme = scheme_of(url)
    if dialect == "motioncal" and scheme != "replay":  # a replay follows its capture's header
        if scheme != "serial":
            raise DeviceError(f"--dialect motioncal needs a serial port or a replay://, not {url!r}")
        scheme = "motioncal"
    elif dialect not in ("native", "auto"):
        raise DeviceError(f"unknown dialect {dialect!r} (native, motioncal, auto)")
    module, _, name = _REGISTRY[scheme].partition(":")
    try:
        factory = getattr(importlib.import_module(module), name)
    except ImportError as exc:
        raise DeviceError(f"backend for {url!r} is unavailable: {exc}") from exc
    return factory(url, dialect=dialect, **options)


__all__ = ["Device", "Event", "Identity", "Item", "open_device", "scheme_of"]
