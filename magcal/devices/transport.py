"""Transports and connectors: the byte plumbing under the devices that speak over a port.

A transport is pyserial-shaped (``read``, ``write``, ``in_waiting``, a settable ``timeout``,
``close``). A *connector* is what a device calls to get one, once per connection: called again
after a close, it connects again (``SerialPort`` opens the port anew; a simulated board is
plugged back in). ``WrappedTransport`` forwards everything to ``inner``; a subclass overrides
only what it changes (a capture tap records what ``read`` returns).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from ..core.errors import PortUnavailable

if TYPE_CHECKING:
    from ..recordings.capture import CaptureWriter

Connector = Callable[[], object]  # () → an open transport; PortUnavailable when it cannot


class SerialPort:
    """The connector of a serial port or pyserial URL (``/dev/ttyACM0``, ``socket://…``):
    each call opens it. ``first``: a port already opened (by a dialect detection) for the
    first call."""

    def __init__(self, url: str, baud: int = 115200, first=None):
        self.url = url
        self.baud = int(baud)
        self._first = first

    def __call__(self):
        if self._first is not None:
            port, self._first = self._first, None
            return port
        import serial  # pyserial

        from .portlock import is_device_path, open_exclusive

        try:
            if is_device_path(self.url):  # one process per port (``portlock``): PortBusy names the holder
                return open_exclusive(serial, self.url, self.baud, 0.05)
            return serial.serial_for_url(self.url, baudrate=self.baud, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortUnavailable(f"cannot open {self.url}: {exc}") from exc


class WrappedTransport:
    def __init__(self, inner):
        self.inner = inner

    def read(self, n: int = 1) -> bytes:
        return self.inner.read(n)

    def write(self, data: bytes) -> int:
        return self.inner.write(data)

    @property
    def in_waiting(self) -> int:
        return self.inner.in_waiting

    @property
    def timeout(self):
        return self.inner.timeout

    @timeout.setter
    def timeout(self, value) -> None:
        self.inner.timeout = value

    def close(self) -> None:
        self.inner.close()


class TapTransport(WrappedTransport):
    """A pyserial-like transport that records every byte read from the one it wraps."""

    def __init__(self, inner, writer: "CaptureWriter"):
        super().__init__(inner)
        self.writer = writer

    def read(self, n: int = 1) -> bytes:
        err = self.writer.take_error()
        if err is not None:
            raise err  # nothing was read in this call, so nothing is lost
        data = self.inner.read(n)
        if data:
            self.writer.append(data)
        return data

    @property
    def in_waiting(self) -> int:
        if self.writer.failing:
            return 0  # let the caller finish with what it has; the next read reports
        return self.inner.in_waiting

    def close(self) -> None:
        try:
            self.inner.close()
        finally:
            self.writer.flush()

    def __getattr__(self, name):  # reset_input_buffer, dtr, … of the wrapped transport
        return getattr(self.inner, name)


def tapped(transport, capture):
    """``transport`` with every byte read also appended to ``capture`` (a
    ``magcal.recordings.capture.CaptureWriter``); the transport itself when ``capture`` is None."""
    return transport if capture is None else TapTransport(transport, capture)
