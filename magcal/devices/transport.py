"""A transport that wraps another: the shared plumbing of taps and fault injectors.

A transport is pyserial-shaped (``read``, ``write``, ``in_waiting``, a settable ``timeout``,
``close``). ``WrappedTransport`` forwards all of it to ``inner``; a subclass overrides only what
it changes (a capture tap records what ``read`` returns, a fault injector fails or delays it).
"""

from __future__ import annotations


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
