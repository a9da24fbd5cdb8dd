"""``replay://FILE[?pace=X]`` — a recorded capture served as a transport, byte-exact.

The bytes go through the live protocol client (``ProtocolDevice``, passive: it never writes),
so a replay yields exactly what the live link yielded. ``pace=0`` (default) serves the bytes
as fast as they are read; ``pace=1`` at the recorded pace (each chunk released at its receive
time), ``pace=N`` N times faster. The end of the recording → ``read`` raises ``EOFError``.
A capture cut short by a crash replays up to its last whole chunk; the device's counters say
how many bytes were cut (``capture_truncated_bytes``).

Fault injection (for the daemon's tests): ``fault=KIND@T[+D][=N]``, repeatable, at recorded
time T s, always between two recorded lines — ``unplug`` (reads fail for D wall seconds; opening
the same URL again resumes where the replay was, after the recording's hello re-sent with seq 0
as a replugged board would send it), ``stall`` (no bytes for D s), ``garbage`` (N random bytes),
``reset`` (a torn line, then that hello). Same syntax as ``sim://``.
"""

from __future__ import annotations

import time
from typing import Callable, Iterable
from urllib.parse import parse_qs

from ..core.errors import DeviceError, InputError
from .link import ProtocolDevice
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

    def write(self, data: bytes) -> int:
        raise OSError("a replay cannot take commands")

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self._closed = True


def parse_replay_url(url: str) -> tuple[str, float]:
    """``replay://FILE[?pace=X]`` → (path, pace). ``replay:///abs/path`` and
    ``replay://relative/path`` both work."""
    rest = url[len("replay://") :] if url.startswith("replay://") else url
    path, _, query = rest.partition("?")
    if not path:
        raise DeviceError(f"{url!r}: replay:// needs a file, e.g. replay://session.cap")
    q = {k: v[-1] for k, v in parse_qs(query, keep_blank_values=True).items()}
    unknown = set(q) - {"pace", "fault"}
    if unknown:
        raise DeviceError(f"replay:// does not know option(s) {sorted(unknown)}; known: ['fault', 'pace']")
    try:
        pace = float(q.get("pace", 0) or 0)
    except ValueError:
        raise DeviceError(f"replay:// pace must be a number, got {q['pace']!r}") from None
    if pace < 0:
        raise DeviceError("replay:// pace must be ≥ 0 (0 = as fast as read, 1 = recorded pace)")
    return path, pace


REPLAY_FAULTS = ("unplug", "stall", "garbage", "reset")
_FAULTY: dict = {}  # url → FaultyTransport, so a reopened faulty replay resumes in place


class FaultyTransport(WrappedTransport):
    """A ``BytesTransport`` with faults fired at recorded times (see the module docstring)."""

    def __init__(self, inner: BytesTransport, faults, clock: Callable[[], float] = time.monotonic):
        import random

        super().__init__(inner)
        self.faults = sorted(faults)
        self._clock = clock
        self._rng = random.Random(0xFA17)
        self._extra = b""  # injected bytes served before the recording continues
        self._until = {"unplug": 0.0, "stall": 0.0}
        self._closed = False
        self._at_line_end = True  # faults fire between recorded lines, never inside one
        self._hello = self._boot_hello()

    def _boot_hello(self) -> bytes:
        """The recording's first hello, as a freshly booted board sends it (seq 0)."""
        from ..wire.protocol import Hello, classify_line, encode_line

        data = b"".join(c for _, c in self.inner._chunks[:50])
        start = data.find(b"$H,")
        end = data.find(b"\n", start)
        if start < 0 or end < 0:
            return b""
        h = classify_line(data[start:end].rstrip(b"\r"))
        if not isinstance(h, Hello):
            return b""
        return encode_line("H", (0, h.proto, h.firmware, f"{h.who_am_i:02X}", f"{h.wia:02X}", *h.asa, h.rate_hz))

    def _now_s(self) -> float:
        i = min(self.inner._i, len(self.inner._chunks) - 1)
        return self.inner._chunks[i][0] - self.inner._t0_rec if self.inner._chunks else 0.0

    def _due(self) -> bool:
        return bool(self.faults) and self.faults[0][0] <= self._now_s() + 1e-9

    def _fire(self) -> None:
        while self._due():
            _, kind, duration, value = self.faults.pop(0)
            if kind in ("unplug", "stall"):
                self._until[kind] = self._clock() + (0.5 if duration is None else duration)
            elif kind == "garbage":
                self._extra += bytes(self._rng.randrange(256) for _ in range(200 if value is None else int(value)))
            elif kind == "reset":
                self._extra += b"$S,9,12345,1,2"[: self._rng.randrange(3, 14)] + self._hello

    def check_present(self) -> None:
        if self._clock() < self._until["unplug"]:
            raise OSError("replay unplugged (device not present)")

    @property
    def in_waiting(self) -> int:
        if self._clock() < max(self._until.values()):
            return 0
        return len(self._extra) or self.inner.in_waiting

    def read(self, n: int = 1) -> bytes:
        if self._closed:
            raise OSError("replay closed")
        if self._due() and not self._at_line_end:  # finish the line being served first
            out = b""
            while not out.endswith(b"\n"):
                b = self.inner.read(1)
                if not b:
                    break
                out += b
            self._at_line_end = out.endswith(b"\n")
            return out
        self._fire()
        self.check_present()
        if self._clock() < self._until["stall"]:
            self.inner._sleep(min(self.inner.timeout or 0.0, self._until["stall"] - self._clock()))
            return b""
        if self._extra:
            out, self._extra = self._extra[: max(1, n)], self._extra[max(1, n) :]
            return out
        out = self.inner.read(n)
        if out:
            self._at_line_end = out.endswith(b"\n")
        return out

    def reset_input_buffer(self) -> None:
        pass

    def close(self) -> None:
        self._closed = True

    def reopen(self) -> None:
        self.check_present()
        if self._closed:
            self._extra += self._hello  # a replugged board boots and says hello first
        self._closed = False


def replay_faults(url: str) -> list:
    """The ``fault=`` options of a replay URL as (t_s, kind, duration_s, value), sorted."""
    from .simboard import parse_fault

    query = url.partition("?")[2]
    specs = [f for v in parse_qs(query, keep_blank_values=True).get("fault", []) for f in v.split(";") if f]
    faults = [parse_fault(f) for f in specs]
    for f in faults:
        if f[1] not in REPLAY_FAULTS:
            raise DeviceError(f"replay:// cannot inject {f[1]!r}; it can: {', '.join(REPLAY_FAULTS)}")
    return sorted(faults)


def open_replay(url: str, dialect: str = "native", **options):
    """The capture's own convention decides how it is read: protocol v1 through
    ``ProtocolDevice``, a MotionCal-dialect capture through ``MotionCalDevice`` (passive)."""
    from ..recordings.capture import CaptureReader, recorded_dialect

    path, pace = parse_replay_url(url)
    faults = replay_faults(url)
    if faults and url in _FAULTY:
        transport = _FAULTY[url]
        try:
            transport.reopen()
        except OSError as exc:
            from ..core.errors import PortUnavailable

            raise PortUnavailable(f"cannot open {url}: {exc}") from None
        options.pop("baud", None)
        options.pop("sleep", None)
        return ProtocolDevice(url, transport, transport_name="replay", passive=True, **options)
    try:
        reader = CaptureReader(path)
    except InputError as exc:
        raise DeviceError(f"cannot replay {url!r}: {exc}") from exc
    recorded = recorded_dialect(reader)
    if dialect == "motioncal" and recorded != "motioncal":
        raise DeviceError(f"{url}: this capture was recorded in the {recorded!r} dialect, not motioncal")
    transport = BytesTransport(reader, pace=pace, **{k: options.pop(k) for k in ("sleep",) if k in options})
    if recorded == "motioncal":
        if faults:
            raise DeviceError(f"{url}: fault injection replays protocol v1 captures only")
        from .motioncal import MotionCalDevice

        options.pop("baud", None)
        dev = MotionCalDevice(url, transport=transport, passive=True,
                              **{k: v for k, v in options.items() if k in ("open_timeout_s", "tap")})
        dev.capture_header = reader.header
        return dev
    if faults:
        transport = _FAULTY[url] = FaultyTransport(transport, faults)
    options.pop("baud", None)
    dev = ProtocolDevice(url, transport, transport_name="replay", passive=True, **options)
    dev.capture_header = reader.header
    if reader.truncated_bytes:
        dev.counters["capture_truncated_bytes"] = reader.truncated_bytes
    return dev


def collect_samples(dev) -> list:
    """Open a passive device and read it to the end: the samples, in order (events dropped)."""
    from ..core.sample import Sample

    out = []
    dev.open()
    try:
        while True:
            try:
                items = dev.read(0.05)
            except EOFError:
                break
            out.extend(i for i in items if isinstance(i, Sample))
    finally:
        dev.close()
    return out
