"""``replay://FILE[?pace=X]`` — a recorded capture served as a transport, byte-exact.

The bytes go through the live protocol client (``ProtocolDevice``, passive: it never writes),
so a replay yields exactly what the live link yielded. ``pace=0`` (default) serves the bytes
as fast as they are read; ``pace=1`` at the recorded pace (each chunk released at its receive
time), ``pace=N`` N times faster. The end of the recording → ``read`` raises ``EOFError``.
A capture cut short by a crash replays up to its last whole chunk; the device's counters say
how many bytes were cut (``capture_truncated_bytes``).

Opening the device again after a close resumes where the replay was, as a replugged board goes
on streaming. Fault injection (for the daemon's tests): ``fault=KIND@T[+D][=N]``, repeatable, at
recorded time T s, always between two recorded lines — the link faults of
``magcal.devices.faults``: ``unplug`` (reads fail for D wall seconds; a reconnect then gets the
recording's hello re-sent with seq 0, as a replugged board would send it), ``stall`` (no bytes
for D s), ``garbage`` (N random bytes), ``reset`` (a torn line, then that hello).
"""

from __future__ import annotations

import time
from typing import Callable, Iterable

from ..core.errors import DeviceError, InputError, PortError, PortUnavailable
from ..wire.dialect import Dialect
from ..wire.protocol import Hello, classify_line, encode_line
from .faults import FaultKind, LinkFaults
from .protocol_client import ProtocolDevice
from .port import Port
from .transport import WrappedTransport


class BytesTransport:
    """Recorded ``(t_rx_s, bytes)`` chunks as a read-only pyserial-like transport."""

    def __init__(
        self,
        chunks: Iterable[tuple[float, bytes]],
        pace: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self._chunks = [(float(t), bytes(b)) for t, b in chunks if b]
        self.pace = float(pace)
        self.timeout: float | None = 0.05
        self._clock = clock
        self._sleep = sleep
        self._i = 0  # current chunk
        self._off = 0  # offset inside it
        self._t0_rec = self._chunks[0][0] if self._chunks else 0.0
        self._t0_wall: float | None = None
        self._closed = False

    def _due(self, i: int) -> float:
        """Wall-clock seconds until chunk ``i`` may be served (≤ 0: now)."""
        if self.pace <= 0:
            return 0.0
        if self._t0_wall is None:
            self._t0_wall = self._clock()
        return (self._chunks[i][0] - self._t0_rec) / self.pace - (self._clock() - self._t0_wall)

    @property
    def in_waiting(self) -> int:
        if self._i >= len(self._chunks) or self._due(self._i) > 0:
            return 0
        return len(self._chunks[self._i][1]) - self._off

    def read(self, n: int = 1) -> bytes:
        if self._closed:
            raise OSError("replay closed")
        if self._i >= len(self._chunks):
            raise EOFError("end of capture")
        wait = self._due(self._i)
        if wait > 0:
            limit = self.timeout if self.timeout is not None else wait
            self._sleep(min(wait, max(0.0, limit)))
            if self._due(self._i) > 0:
                return b""
        data = self._chunks[self._i][1]
        out = data[self._off : self._off + max(1, n)]
        self._off += len(out)
        if self._off >= len(data):
            self._i += 1
            self._off = 0
        return out

    @property
    def t_rx_s(self) -> float:
        """The recorded receive time of the bytes last served (the first chunk's before any)."""
        if not self._chunks:
            return 0.0
        i = self._i - 1 if self._off == 0 and self._i > 0 else self._i
        return self._chunks[min(i, len(self._chunks) - 1)][0]

    def head(self, chunks: int) -> bytes:
        """The bytes of the first ``chunks`` recorded chunks (what a recording starts with)."""
        return b"".join(c for _, c in self._chunks[:chunks])

    @property
    def t_first_s(self) -> float:
        """The recorded receive time of the first chunk."""
        return self._t0_rec

    @property
    def t_next_s(self) -> float:
        """The recorded receive time of the next chunk to serve (the last one's at the end)."""
        if not self._chunks:
            return 0.0
        return self._chunks[min(self._i, len(self._chunks) - 1)][0]

    def wait(self, seconds: float) -> None:
        """Sleep on this recording's clock (a stalled link waits without serving)."""
        self._sleep(max(0.0, seconds))

    def write(self, data: bytes) -> int:
        raise OSError("a replay cannot take commands")

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self._closed = True

    def reopen(self) -> None:
        self._closed = False


def resuming(transport, url: str):
    """The connector of a recording: the first connection starts it, each later one resumes it
    where the last one stopped (a replugged board goes on streaming)."""

    def connect():
        try:
            transport.reopen()
        except OSError as exc:
            raise PortUnavailable(f"cannot open {url}: {exc}") from None
        return transport

    return connect


TORN_SAMPLE = b"$S,9,12345,1,2,3,0,0*00\n"  # what a reset cuts: the start of some sample line


class FaultyReplay(WrappedTransport):
    """A ``BytesTransport`` with link faults fired at recorded times, always between two recorded
    lines (``magcal.devices.faults``; see the module docstring)."""

    def __init__(self, inner: BytesTransport, faults, clock: Callable[[], float] = time.monotonic):
        super().__init__(inner)
        self.link = LinkFaults(faults, clock)
        self._extra = b""  # injected bytes served before the recording continues
        self._closed = False
        self._at_line_end = True  # faults fire between recorded lines, never inside one
        self._hello = self._boot_hello()

    def _boot_hello(self) -> bytes:
        """The recording's first hello, as a freshly booted board sends it (seq 0)."""
        data = self.inner.head(50)
        start = data.find(b"$H,")
        end = data.find(b"\n", start)
        if start < 0 or end < 0:
            return b""
        h = classify_line(data[start:end].rstrip(b"\r"))
        if not isinstance(h, Hello):
            return b""
        return encode_line("H", (0, h.proto, h.firmware, f"{h.who_am_i:02X}", f"{h.wia:02X}", *h.asa, h.rate_hz,
                                 *(() if h.bits is None else (h.bits,))))

    def _now_s(self) -> float:
        return self.inner.t_next_s - self.inner.t_first_s

    def _fire(self) -> None:
        for fault in self.link.due(self._now_s()):
            if fault.kind in (FaultKind.UNPLUG, FaultKind.STALL):
                self.link.interrupt(fault)
            elif fault.kind is FaultKind.GARBAGE:
                self._extra += self.link.noise(fault.value)
            elif fault.kind is FaultKind.RESET:
                self._extra += self.link.torn(TORN_SAMPLE) + self._hello
        self.link.settle(drained=True)  # a fault fires only once the lines before it were served

    @property
    def in_waiting(self) -> int:
        self.link.settle(drained=True)
        if self.link.stalled or self.link.unplugged:
            return 0
        return len(self._extra) or self.inner.in_waiting

    def read(self, n: int = 1) -> bytes:
        if self._closed:
            raise OSError("replay closed")
        if self.link.next_s() <= self._now_s() + 1e-9 and not self._at_line_end:
            return self._finish_line()
        self._fire()
        self.link.check_present("replay")
        if self.link.stalled:
            self.inner.wait(min(self.inner.timeout or 0.0, self.link.quiet_s()))
            return b""
        if self._extra:
            out, self._extra = self._extra[: max(1, n)], self._extra[max(1, n) :]
            return out
        out = self.inner.read(n)
        if out:
            self._at_line_end = out.endswith(b"\n")
        return out

    def _finish_line(self) -> bytes:
        """The rest of the line being served, so that a due fault lands between two lines."""
        out = b""
        while not out.endswith(b"\n"):
            b = self.inner.read(1)
            if not b:
                break
            out += b
        self._at_line_end = out.endswith(b"\n")
        return out

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self._closed = True

    def reopen(self) -> None:
        self.link.settle(drained=True)
        self.link.check_present("replay")
        if self._closed:
            self._extra += self._hello  # a replugged board boots and says hello first
        self._closed = False


def open_replay(port: Port, dialect: Dialect = Dialect.NATIVE, *, tap=None, baud: int | None = None,
                reply_timeout_s: float = 1.5, open_timeout_s: float = 3.0,
                clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
    """The capture's own convention decides how it is read: protocol v1 through
    ``ProtocolDevice``, a MotionCal-dialect capture through ``MotionCalDevice`` (passive).
    ``baud`` is taken and ignored (a recording has no baud rate); ``reply_timeout_s`` and
    ``open_timeout_s``: options of the client that reads it. ``clock`` and ``sleep``: the time
    the replay's pace, its faults and the protocol client keep (a fake clock makes a stall last
    its stated time however slowly the reader works)."""
    from ..recordings.capture import CaptureReader, recorded_dialect

    try:
        reader = CaptureReader(port.target)
    except InputError as exc:
        raise DeviceError(f"cannot replay {port.url!r}: {exc}") from exc
    try:
        recorded = recorded_dialect(reader)
    except InputError as exc:
        raise DeviceError(f"cannot replay {port.url!r}: {exc}") from exc
    if dialect is Dialect.MOTIONCAL and recorded is not Dialect.MOTIONCAL:
        # the capture will not change: a setting no retry can help (PortError), not a device fault
        raise PortError(f"{port.url}: this capture was recorded in the {recorded.value!r} dialect, not motioncal "
                        "(--dialect auto or native reads it)")
    transport = BytesTransport(reader, pace=port.get("pace", 0.0), clock=clock, sleep=sleep)
    if port.faults:
        if recorded is Dialect.MOTIONCAL:
            raise PortError(f"{port.url}: fault injection replays protocol v1 captures only")
        transport = FaultyReplay(transport, port.faults, clock=clock)
    dev = recorded_device(port.url, transport, recorded, tap=tap, reply_timeout_s=reply_timeout_s,
                          open_timeout_s=open_timeout_s, clock=clock)
    if reader.truncated_bytes:
        dev.counters["capture_truncated_bytes"] = reader.truncated_bytes
    return dev


def recorded_device(url: str, transport, dialect: Dialect = Dialect.NATIVE, *, tap=None, reply_timeout_s: float = 1.5,
                    open_timeout_s: float = 3.0, clock: Callable[[], float] = time.monotonic):
    """The client that reads a recording (``BytesTransport``, possibly faulty) as it was read
    live, listening only: ``ProtocolDevice`` for protocol v1, ``MotionCalDevice`` for the
    MotionCal convention, each reading timed by when its bytes arrived."""
    if dialect is Dialect.MOTIONCAL:
        from .motioncal_client import MotionCalDevice

        return MotionCalDevice(url, connect=resuming(transport, url), passive=True, tap=tap,
                               data_clock=lambda: transport.t_rx_s, open_timeout_s=open_timeout_s)
    return ProtocolDevice(url, resuming(transport, url), transport_name="replay", passive=True,
                          tap=tap, reply_timeout_s=reply_timeout_s, clock=clock)
