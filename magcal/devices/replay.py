"""``replay://FILE[?pace=X]`` — a recorded capture served as a transport, byte-exact.

The bytes go through the live protocol client (``ProtocolDevice``, passive: it never writes),
so a replay yields exactly what the live link yielded. ``pace=0`` (default) serves the bytes
as fast as they are read; ``pace=1`` at the recorded pace (each chunk released at its receive
time), ``pace=N`` N times faster. The end of the recording → ``read`` raises ``EOFError``.
A capture cut short by a crash replays up to its last whole chunk; the device's counters say
how many bytes were cut (``capture_truncated_bytes``).
"""

from __future__ import annotations

import time
from typing import Callable, Iterable
from urllib.parse import parse_qs

from ..errors import DeviceError, InputError
from .link import ProtocolDevice


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
    unknown = set(q) - {"pace"}
    if unknown:
        raise DeviceError(f"replay:// does not know option(s) {sorted(unknown)}; known: ['pace']")
    try:
        pace = float(q.get("pace", 0) or 0)
    except ValueError:
        raise DeviceError(f"replay:// pace must be a number, got {q['pace']!r}") from None
    if pace < 0:
        raise DeviceError("replay:// pace must be ≥ 0 (0 = as fast as read, 1 = recorded pace)")
    return path, pace


def open_replay(url: str, dialect: str = "native", **options) -> ProtocolDevice:
    from ..capture import CaptureReader

    path, pace = parse_replay_url(url)
    try:
        reader = CaptureReader(path)
    except InputError as exc:
        raise DeviceError(f"cannot replay {url!r}: {exc}") from exc
    recorded = reader.header.get("dialect") or "native"
    if recorded != "native":
        raise DeviceError(f"{url}: this capture was recorded in the {recorded!r} dialect; replay:// speaks protocol v1")
    transport = BytesTransport(reader, pace=pace, **{k: options.pop(k) for k in ("sleep",) if k in options})
    options.pop("baud", None)
    dev = ProtocolDevice(url, transport, transport_name="replay", passive=True, **options)
    dev.capture_header = reader.header
    if reader.truncated_bytes:
        dev.counters["capture_truncated_bytes"] = reader.truncated_bytes
    return dev


def collect_samples(dev) -> list:
    """Open a passive device and read it to the end: the samples, in order (events dropped)."""
    from ..sample import Sample

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
