"""Fault injection for the simulated sources: one vocabulary, one schedule, one injector.

A fault is written ``KIND[@T][+D][=VALUE]`` (the ``fault=`` option of a port string, repeatable):
it fires when the source's own time reaches T seconds — the physics time of ``sim://``, the
recorded time of ``replay://`` — and lasts D wall-clock seconds where that means something.

Link faults (``sim://`` and ``replay://``), acted out by ``LinkFaults`` on the bytes:

- ``unplug@T+D``: the port vanishes for D s (default 0.5): reads, writes and opens fail with
  ``OSError``; when it comes back the source boots afresh, as a USB reconnect resets a board;
- ``stall@T+D``: no bytes out and no command taken for D s (default 1);
- ``reset@T``: a line torn in the middle, then a fresh boot hello (seq 0);
- ``garbage@T=N``: a burst of N random bytes (default 200) between two lines.

``unplug`` and ``stall`` take effect once the host has read what the source sent before T, so a
test knows exactly which lines came first. Board faults (``sim://`` only): ``hard_iron@T=x,y,z``
(the physics' hard iron becomes x, y, z µT), ``mute``, ``no_write_ack``, ``corrupt_write`` (that
behaviour from T on; ``corrupt_write`` spoils the next write only). Register-model faults
(``emu://``, and ``FakeBus`` for ``i2c:``): ``wrong_whoami``, ``no_ak``, ``stuck_drdy``,
``wrong_wia`` — flags of the one C register model, in effect from power-up.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Callable, Iterable

from ..core.errors import PortError
from ..core.events import Code

NOISE_SEED = 0xFA17  # the random bytes of garbage bursts and torn lines: the same on every run


class FaultKind(Code):
    UNPLUG = "unplug"
    STALL = "stall"
    RESET = "reset"
    GARBAGE = "garbage"
    HARD_IRON = "hard_iron"
    MUTE = "mute"
    NO_WRITE_ACK = "no_write_ack"
    CORRUPT_WRITE = "corrupt_write"
    WRONG_WHOAMI = "wrong_whoami"
    NO_AK = "no_ak"
    STUCK_DRDY = "stuck_drdy"
    WRONG_WIA = "wrong_wia"


LINK_FAULTS = frozenset({FaultKind.UNPLUG, FaultKind.STALL, FaultKind.RESET, FaultKind.GARBAGE})
BOARD_FAULTS = frozenset({FaultKind.HARD_IRON, FaultKind.MUTE, FaultKind.NO_WRITE_ACK, FaultKind.CORRUPT_WRITE})
# the C register model's fault flags (firmware/emulator/mpu9150_model.h)
REGISTER_FAULTS = {
    FaultKind.WRONG_WHOAMI: 1 << 0,
    FaultKind.NO_AK: 1 << 1,
    FaultKind.STUCK_DRDY: 1 << 2,
    FaultKind.WRONG_WIA: 1 << 3,
}
DEFAULT_DURATION_S = {FaultKind.UNPLUG: 0.5, FaultKind.STALL: 1.0}
DEFAULT_GARBAGE_BYTES = 200


@dataclass(frozen=True)
class Fault:
    t_s: float
    kind: FaultKind
    duration_s: float | None = None
    value: object = None


def parse_fault(spec: str, allowed: Iterable[FaultKind] = tuple(FaultKind), where: str = "") -> Fault:
    """``KIND[@T][+D][=VALUE]`` → Fault; ``PortError`` naming the problem when malformed or
    when ``KIND`` is not among ``allowed``."""
    allowed = tuple(allowed)
    head, _, value = spec.partition("=")
    head, _, dur = head.replace(" ", "+").partition("+")  # a '+' in a URL query arrives as ' '
    name, _, at = head.partition("@")
    known = ", ".join(k.value for k in allowed)
    try:
        kind = FaultKind(name.strip())
    except ValueError:
        raise PortError(f"{where}unknown fault {name.strip()!r} in {spec!r}; known: {known}") from None
    if kind not in allowed:
        raise PortError(f"{where}cannot inject {kind.value!r}; it can: {known}")
    try:
        t_s = float(at.rstrip("s")) if at else 0.0
        duration = float(dur.rstrip("s")) if dur else None
        val = _fault_value(kind, value)
    except ValueError as exc:
        raise PortError(f"{where}bad fault {spec!r}: {exc}") from None
    if t_s < 0 or (duration is not None and duration < 0):
        raise PortError(f"{where}bad fault {spec!r}: times must be ≥ 0")
    if kind in REGISTER_FAULTS and (t_s or duration is not None or value):
        raise PortError(f"{where}fault {kind.value!r} is a register-model flag, in effect from power-up: "
                        "give it without @T, +D or =VALUE")
    return Fault(t_s, kind, duration, val)


def _fault_value(kind: FaultKind, value: str):
    if kind is FaultKind.HARD_IRON:
        v = tuple(float(x) for x in value.split(","))
        if len(v) != 3:
            raise ValueError("hard_iron takes x,y,z in µT")
        return v
    if kind is FaultKind.GARBAGE:
        n = int(value) if value else None
        if n is not None and n < 0:
            raise ValueError("garbage takes a number of bytes ≥ 0")
        return n
    return None


def register_flags(faults: Iterable[Fault]) -> int:
    """The register model's fault bit mask for the register-model faults among ``faults``."""
    flags = 0
    for f in faults:
        flags |= REGISTER_FAULTS.get(f.kind, 0)
    return flags


class LinkFaults:
    """The one injector: a schedule of faults and the state of the link they act on.

    The source (a simulated board, a recording) asks ``due(now_s)`` for the faults its time has
    reached and acts them out with this object's help; it calls ``settle(drained)`` before
    every byte it moves, and honours ``stalled`` and ``check_present``.
    """

    def __init__(self, faults: Iterable[Fault] = (), clock: Callable[[], float] = time.monotonic,
                 seed: int = NOISE_SEED):
        self.pending = sorted(faults, key=lambda f: f.t_s)
        self.fired: list[tuple[float, FaultKind]] = []  # what went off, at what source time
        self._clock = clock
        self._rng = random.Random(seed)
        self._armed: dict[FaultKind, float] = {}  # unplug/stall waiting for the host to drain
        self._until: dict[FaultKind, float] = {}  # wall-clock end of an unplug/stall in effect

    # -- the schedule -------------------------------------------------------------------------
    def next_s(self) -> float:
        """Source time of the next scheduled fault (infinity when none is left)."""
        return self.pending[0].t_s if self.pending else float("inf")

    def due(self, now_s: float) -> list[Fault]:
        """The faults whose time has come, in order, taken off the schedule."""
        n = 0
        while n < len(self.pending) and self.pending[n].t_s <= now_s + 1e-9:
            n += 1
        out, self.pending = self.pending[:n], self.pending[n:]
        self.fired.extend((now_s, f.kind) for f in out)
        return out

    # -- acting them out ------------------------------------------------------------------------
    def interrupt(self, fault: Fault) -> None:
        """Start an unplug or a stall (from the moment the host has drained the link)."""
        self._armed[fault.kind] = DEFAULT_DURATION_S[fault.kind] if fault.duration_s is None else fault.duration_s

    def noise(self, n: int | None = None) -> bytes:
        """A garbage burst: ``n`` random bytes (default 200)."""
        return self._rng.randbytes(DEFAULT_GARBAGE_BYTES if n is None else int(n))

    def torn(self, line: bytes) -> bytes:
        """The start of ``line`` as a reset cuts it: never the whole line."""
        return line[: self._rng.randrange(3, max(4, len(line) - 1))]

    def settle(self, drained: bool) -> bool:
        """Start armed interruptions once ``drained``; end those whose time is over. True when
        an unplug has just ended: the source boots, as a replugged board does."""
        now = self._clock()
        if drained and self._armed:
            for kind, duration in self._armed.items():
                self._until[kind] = now + duration
            self._armed.clear()
        ended = [k for k, t in self._until.items() if now >= t]
        for k in ended:
            del self._until[k]
        return FaultKind.UNPLUG in ended

    @property
    def waiting(self) -> bool:
        """An unplug or stall is due, waiting for the host to read what came before it."""
        return bool(self._armed)

    @property
    def stalled(self) -> bool:
        return FaultKind.STALL in self._until

    @property
    def unplugged(self) -> bool:
        return FaultKind.UNPLUG in self._until

    def check_present(self, what: str) -> None:
        """``OSError`` while unplugged, as the operating system reports a vanished port."""
        if self.unplugged:
            raise OSError(f"{what} unplugged (device not present)")

    def quiet_s(self) -> float:
        """Wall seconds until the current stall or unplug ends (0 when none is in effect)."""
        return max([0.0] + [t - self._clock() for t in self._until.values()])
