"""Which device a command talks to when no ``--port`` was given.

There is no default device: ``--port``, ``$MAGCAL_PORT`` or the config file's ``port`` name one.
When none does, the serial devices plugged in are listed: exactly one is used (and named on
stderr); otherwise, at a terminal, the user is asked; elsewhere the command stops with a usage
error that says how to name a device. The simulator is used only when named (``sim://``).
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass

from ..core.errors import ConfigError

HOW = ("name one with --port (e.g. --port /dev/ttyACM0, COM3, i2c:1; --port sim:// for the "
       "simulated board), MAGCAL_PORT=… in the environment, or port: in the config file")


@dataclass(frozen=True)
class Candidate:
    device: str
    description: str


def serial_candidates() -> list[Candidate]:
    """The USB serial devices plugged in (a motherboard's phantom ttyS ports are left out)."""
    try:
        from serial.tools import list_ports
    except ImportError:  # pragma: no cover - pyserial is a dependency
        return []
    found = []
    for p in list_ports.comports():
        if p.vid is None and (p.hwid in (None, "", "n/a")):
            continue
        found.append(Candidate(p.device, p.description if p.description not in (None, "n/a") else p.hwid))
    return sorted(found, key=lambda c: c.device)


def choose_port(found: list[Candidate], ask=None, say=None) -> str:
    """The port to use when none was named: the one candidate (said through ``say``), or what
    ``ask(prompt)`` answers (None when nobody can be asked), else ConfigError saying how."""
    if len(found) == 1:
        if say:
            say(f"magcal: no --port given; using the one serial device found: {found[0].device} "
                f"({found[0].description})")
        return found[0].device
    listing = "".join(f"\n  {c.device}  {c.description}" for c in found)
    if ask is not None:
        head = (f"{len(found)} serial devices found:{listing}\n" if found
                else "no serial device found (is the board plugged in?)\n")
        answer = (ask(head + "port to use (a device above, or sim:// for the simulator): ") or "").strip()
        if answer:
            return answer
    if found:
        raise ConfigError(f"no device named and {len(found)} serial devices plugged in:{listing}\n{HOW}")
    raise ConfigError(f"no device named and no serial device found: {HOW}")


def _ask_on_terminal():
    if not (sys.stdin.isatty() and sys.stderr.isatty()):
        return None

    def ask(prompt: str) -> str:
        sys.stderr.write(prompt)
        sys.stderr.flush()
        try:
            return sys.stdin.readline()
        except KeyboardInterrupt:
            return ""

    return ask


def with_port(settings):
    """``settings`` with a port: the one named, the one plugged in, or the user's answer."""
    if settings.port:
        return settings
    port = choose_port(serial_candidates(), ask=_ask_on_terminal(),
                       say=lambda m: print(m, file=sys.stderr, flush=True))
    return dataclasses.replace(settings, port=port)
