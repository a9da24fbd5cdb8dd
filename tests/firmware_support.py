"""What the firmware tests need: the AVR toolchain and simavr, or a clear reason they are absent.

When the toolchain is missing the firmware tests skip with the reason — except under CI
(``CI=true``), where the toolchain is installed on purpose and its absence is a failure.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import time

import pytest

from magcal.devices.emulator import ELF, FIRMWARE_DIR, HARNESS, ensure_built, toolchain_problem
from magcal.wire.protocol import Framer, encode_command

_built = False


def require_firmware() -> None:
    """Bring the firmware and harness up to date with the sources (make is incremental), or
    skip — fail under CI — when the toolchain is absent."""
    global _built
    problem = toolchain_problem()
    if problem is not None:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true but the firmware cannot be built: {problem}")
        pytest.skip(problem)
    if not _built:
        # the test processes (pytest -n) share one build directory: one make at a time, the
        # others then find everything up to date
        lock_dir = FIRMWARE_DIR / "build"
        lock_dir.mkdir(exist_ok=True)
        with open(lock_dir / ".tests.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            for target in (FIRMWARE_DIR, FIRMWARE_DIR / "emulator"):
                r = subprocess.run(["make", "-C", str(target)], capture_output=True, text=True)
                assert r.returncode == 0, f"make -C {target} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
            ensure_built()
        _built = True
    ensure_built()


class RawBoard:
    """The harness driven with raw pyserial on its pty: protocol-level tests with no host client.

    ``lines`` are the framer's items in arrival order. ``eager``: each read returns what has
    arrived instead of waiting out the port's 50 ms timeout for a full buffer — for a test that
    waits for every reply it expects before it writes again (the board's 64-byte receive buffer
    overflows when a host writes a long line while the board is still sending a long reply)."""

    def __init__(self, tmp_path, field=(100, -200, 300), eeprom=None, extra=(), eager=False):
        import serial

        self.eeprom = str(eeprom or (tmp_path / "eeprom.bin"))
        cmd = [str(HARNESS), "--field", ",".join(str(v) for v in field), "--eeprom", self.eeprom,
               *extra, str(ELF)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        assert line.startswith("PTY "), f"harness said {line!r}"
        self.port = serial.Serial(line.split()[1], 115200, timeout=0.05)
        self.framer = Framer()
        self.items: list = []  # everything received, in order
        self._unseen: list = []  # received but not yet looked at by wait_for/pump
        self._tag = 0
        self._eager = eager

    def send(self, cmd: str, *args) -> int:
        self._tag += 1
        self.port.write(encode_command(cmd, self._tag, *args))
        return self._tag

    def write(self, data: bytes) -> None:
        self.port.write(data)

    def _receive(self) -> None:
        data = self.port.read(max(1, self.port.in_waiting) if self._eager else 4096)
        if data:
            got = self.framer.feed(data)
            self.items.extend(got)
            self._unseen.extend(got)

    def pump(self, seconds: float) -> list:
        """Collect everything that arrives for ``seconds``; returns the items not yet seen."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._receive()
        new, self._unseen = self._unseen, []
        return new

    def wait_for(self, pred, timeout_s: float = 5.0, what: str = "reply"):
        """The first not-yet-seen item matching ``pred`` (items before it count as seen)."""
        end = time.monotonic() + timeout_s
        seen = []
        while True:
            while self._unseen:
                item = self._unseen.pop(0)
                seen.append(item)
                if pred(item):
                    return item
            if time.monotonic() >= end:
                raise AssertionError(f"no {what} within {timeout_s} s; saw {seen[-5:]}")
            self._receive()

    def close(self) -> str:
        """Stop the harness; returns what it wrote to stderr."""
        if self.proc.returncode is not None:
            return ""
        self.port.close()
        self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
        return err


def make_size_output() -> str:
    r = subprocess.run(["make", "-C", str(FIRMWARE_DIR), "size"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r.stdout
