"""A serial device that speaks the PJRC MotionCal / Adafruit convention (``--dialect motioncal``).

The board streams ``Raw:``/``Uni:`` lines on its own (there are no commands, so ``start`` and
``stop`` only mark the session); ``write_calibration`` sends the 68-byte packet and waits for
the ``Cal1:``/``Cal2:`` echo, which it checks at the echo's printed precision. The pure rules
live in ``magcal.wire.motioncal``; this module only moves bytes and watches the clock.

Samples: ``field_ut`` from the magnetometer (Uni: µT while the device sends them, else Raw:
counts × 0.1), ``raw`` None, ``seq`` counted here (the convention has none), ``t_s`` the host's
arrival time in seconds since ``open`` (the convention carries no device time).

Options (``open_device(url, dialect="motioncal", **opts)``): ``baud`` (115200),
``open_timeout_s`` (3: how long ``open`` waits for the first reading; 0 skips the check),
``echo_timeout_s`` (6: per attempt; the Adafruit sketch prints Cal1/Cal2 only every ~100
loops), ``tries`` (3), ``accel_offset``/``gyro_offset`` (sent in the packet; by default the
device's own, from its last Cal1 echo, else zeros), ``tap`` (a capture writer that records every byte read, e.g. a
capture writer that records every byte read).

A recorded session (``replay://`` of a capture in this dialect) is the same device on the
recording's connector with ``passive=True``: it never writes, and a sample's ``t_s`` is the
recorded receive time of its bytes (``data_clock``), as it was live.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Iterable

from ..core.calibration import Calibration
from ..core.errors import DeviceError, NoReply, PortUnavailable, WriteRejected
from ..core.sample import Sample
from ..wire import motioncal as mc
from ..wire.dialect import Dialect
from .base import RECORDING, Abilities, Device, Identity, Item
from .transport import Connector, SerialPort, tapped

_QUEUE_MAX = 100_000
# More than a port can hold buffered between the device and us (Linux: a 4 KB line-discipline
# buffer in front of a tty buffer limited to 64 KB), plus one read's worth: any line received
# after this many bytes since the packet went out was printed after the device got it.
BACKLOG_BYTES = (4 + 64 + 4) * 1024


class MotionCalDevice(Device):
    """A ``Raw:``-printing board (PJRC / Adafruit calibration sketches) on a serial port."""

    #: keyword arguments for ``Calibration.close_to`` when comparing a write with its echo
    compare_tolerance = mc.compare_tolerance()
    abilities = Abilities(live=True, store=True)

    def __init__(
        self,
        url: str,
        baud: int = 115200,
        open_timeout_s: float = 3.0,
        echo_timeout_s: float = 6.0,
        tries: int = 3,
        accel_offset=None,
        gyro_offset=None,
        tap=None,
        connect: Connector | None = None,
        passive: bool = False,
        data_clock=time.monotonic,
    ):
        super().__init__(url)
        if tries < 1 or echo_timeout_s <= 0:
            raise DeviceError("motioncal: tries must be ≥ 1 and echo_timeout_s > 0")
        self.baud = int(baud)
        self.open_timeout_s = float(open_timeout_s)
        self.echo_timeout_s = float(echo_timeout_s)
        self.tries = int(tries)
        self.accel_offset = accel_offset
        self.gyro_offset = gyro_offset
        self._tap = tap  # a capture writer: sees every byte read (transport.tapped)
        self._connect = connect or SerialPort(url, self.baud)
        self.passive = bool(passive)  # a recording: nothing is ever written
        if self.passive:
            self.abilities = RECORDING
        # a sample's time: the host's clock live, the recorded receive time on a replay
        self._data_clock = data_clock
        self._t0_data = 0.0
        self._ser = None
        self._splitter = mc.LineSplitter()
        self._asm = mc.SampleAssembler()
        self._queue: deque = deque(maxlen=_QUEUE_MAX)
        self._seq = 0
        self._t0 = 0.0
        self._echoed: Calibration | None = None
        self.last_echo_mismatch: list[str] = []
        self._last_pair: tuple | None = None

    # -- bytes in ----------------------------------------------------------------------------
    def _pull(self, wait_s: float) -> list[mc.Line]:
        """Read what the port has (waiting up to ``wait_s`` for the first byte) → parsed lines;
        every reading is queued as a Sample."""
        ser = self._ser
        try:
            wait_s = round(max(0.0, wait_s), 3)
            if ser.timeout != wait_s:  # setting it reconfigures the port: only when it changes
                ser.timeout = wait_s
            data = ser.read(max(1, ser.in_waiting))
            if data and ser.in_waiting:
                data += ser.read(ser.in_waiting)
        except EOFError:  # the end of a recording
            raise
        except Exception as exc:  # pyserial raises SerialException/OSError when unplugged
            raise PortUnavailable(f"{self.url}: {exc}") from exc
        if not data:
            return []
        self.counters["bytes"] += len(data)
        lines = []
        for raw in self._splitter.feed(data):
            line = mc.parse_line(raw)
            lines.append(line)
            field = self._asm.push(line)
            if field is not None:
                self._queue.append(
                    Sample(seq=self._seq % 65536, t_s=self._data_clock() - self._t0_data, field_ut=field,
                           aux=accel_aux(line))
                )
                self._seq += 1
            elif isinstance(line, mc.CalLine):
                self._note_echo()
        self._sync_counters()
        return lines

    def _sync_counters(self) -> None:
        for k, v in self._asm.counters.items():
            self.counters[k] = v
        self.counters["overlong"] = self._splitter.counters["overlong"]

    def _note_echo(self) -> None:
        c1, c2 = self._asm.last_cal1, self._asm.last_cal2
        if c1 is not None and c2 is not None:
            cal = mc.calibration_from_echo(c1, c2)
            if cal is not None:
                self._echoed = cal

    # -- Device hooks ----------------------------------------------------------------------
    def _open(self) -> Identity:
        self._ser = tapped(self._connect(), self._tap)
        self._splitter = mc.LineSplitter()  # a new connection: no half line carried over
        self._t0 = time.monotonic()
        self._t0_data = self._data_clock()
        if self.open_timeout_s > 0:
            deadline = self._t0 + self.open_timeout_s
            try:
                while not self._queue and time.monotonic() < deadline:
                    self._pull(min(0.05, max(0.0, deadline - time.monotonic())))
            except EOFError:
                pass  # a recording that ends before its first reading: refused just below
            if not self._queue:
                self._ser.close()
                if self.passive:
                    raise DeviceError(f"{self.url}: the recording holds no Raw: or Uni: line "
                                      f"({self.counters['lines']} other lines)")
                raise NoReply(
                    f"{self.url}: no Raw: or Uni: line within {self.open_timeout_s:g} s at "
                    f"{self.baud} baud ({self.counters['lines']} other lines): is a MotionCal/"
                    "Adafruit calibration sketch running, at this baud rate?"
                )
        return Identity(
            transport="replay" if self.passive else "motioncal",
            proto=0,
            firmware="",
            asa=(128, 128, 128),
            rate_hz=0,
            extra={"dialect": "motioncal", "baud": self.baud},
        )

    def _start(self, rate_hz: int | None) -> None:
        """The convention has no commands: the board streams from reset at its own rate."""
        if rate_hz:
            self.counters["rate_request_ignored"] += 1

    def _stop(self) -> None:
        pass

    def _receive(self, wait_s: float) -> Iterable[Item]:
        if not self._queue:
            self._pull(min(max(0.0, wait_s), 0.05))
        out = list(self._queue)
        self._queue.clear()
        return out

    def _read_calibration(self) -> Calibration | None:
        """The calibration of the last complete Cal1/Cal2 echo seen, or None. Right after
        ``open`` it listens until one echo period (``echo_timeout_s``) has passed since the
        port was opened, since the sketches print Cal1/Cal2 only now and then; readings that
        arrive meanwhile are kept for ``read``. A recording is not listened ahead of: what it
        has echoed so far."""
        if self._echoed is None and self._ser is not None and not self.passive:
            deadline = self._t0 + self.echo_timeout_s
            while self._echoed is None and time.monotonic() < deadline:
                self._pull(min(0.05, max(0.0, deadline - time.monotonic())))
        return self._echoed

    def prepare(self, cal: Calibration) -> Calibration:
        """``cal`` as the device will hold it: float32 numbers, and only hard iron, soft iron
        and field — the packet has no room for temperature, current or drift terms, so those
        are dropped here (counted under ``terms_dropped``) rather than refused at the write."""
        if cal.coef_ut_per_unit:
            self.counters["terms_dropped"] += len(cal.coef_ut_per_unit)
            cal = Calibration(offset_ut=cal.offset_ut, field_ut=cal.field_ut, soft_iron=cal.soft_iron)
        acc, gyr = self._offsets()
        return mc.calibration_from_packet(mc.decode_packet(mc.encode_packet(cal, acc, gyr)))

    def matches(self, sent: Calibration, stored: Calibration | None) -> bool:
        """Equal at the precision the Cal1/Cal2 echo is printed with (3 and 4 decimals)."""
        return stored is not None and sent.close_to(stored, **self.compare_tolerance)

    def _offsets(self) -> tuple[tuple, tuple]:
        c1 = self._asm.last_cal1
        acc = self.accel_offset
        gyr = self.gyro_offset
        if acc is None:
            acc = c1.values[0:3] if c1 is not None else (0.0, 0.0, 0.0)
        if gyr is None:
            gyr = c1.values[3:6] if c1 is not None else (0.0, 0.0, 0.0)
        acc = tuple(0.0 if v != v else v for v in acc)  # an echoed nan is not worth keeping
        gyr = tuple(0.0 if v != v else v for v in gyr)
        return acc, gyr

    def _write_calibration(self, cal: Calibration) -> Calibration:
        """Send the packet, wait for a Cal1 and a Cal2 that both arrive after it and match it
        at their printed precision; resend up to ``tries`` times. Returns the echoed
        calibration; NoReply when no echo ever comes, WriteRejected when echoes come but never
        match."""
        acc, gyr = self._offsets()
        try:
            packet = mc.encode_packet(cal, acc, gyr)
        except ValueError as exc:
            raise DeviceError(f"{self.url}: {exc}") from exc
        sent = mc.packet_values(cal, acc, gyr)
        self.last_echo_mismatch = []
        self._echo_stats = [0, 0]  # complete echoes seen, "couldn't save" warnings
        before = self._read_calibration()  # what it holds now (waits one echo period at most)
        self._last_pair = None
        for attempt in range(1, self.tries + 1):
            self._drain()  # lines that waited in the OS buffer predate the packet
            self._send(packet)
            self.counters["packets_sent"] += 1
            if self._await_echo(sent):
                return self._echoed
            self.counters["echo_retries"] += attempt < self.tries
        echoes, warned = self._echo_stats
        total = self.echo_timeout_s * self.tries
        if echoes == 0:
            listened = time.monotonic() - self._t0
            never = (
                f" (nor any Cal1/Cal2 line in {listened:.0f} s on this port: the sketch does not "
                "print them at all)" if self._asm.counters["cal1"] + self._asm.counters["cal2"] == 0 else ""
            )
            raise NoReply(
                f"{self.url}: no Cal1/Cal2 echo within {total:g} s after {self.tries} tries: "
                f"the firmware probably has no calibration packet handler{never}"
            )
        hint = " (the device reported it could not save)" if warned else ""
        last = mc.calibration_from_echo(*self._last_pair) if self._last_pair else None
        if not hint and before is not None and last is not None and last.close_to(before, **self.compare_tolerance):
            hint = (" (it still reports the calibration it had before: the sketch prints Cal1/Cal2"
                    " but probably has no packet handler)")
        raise WriteRejected(
            f"{self.url}: the device echoed a different calibration after {self.tries} tries"
            f"{hint}: " + "; ".join(self.last_echo_mismatch[:6])
        )

    def _drain(self, max_rounds: int = 1000) -> None:
        """Parse everything already buffered on the port (samples are kept, not lost)."""
        for _ in range(max_rounds):
            try:
                waiting = self._ser.in_waiting
            except Exception as exc:
                raise PortUnavailable(f"{self.url}: {exc}") from exc
            if not waiting:
                return
            self._pull(0.0)

    def _await_echo(self, sent: tuple) -> bool:
        """One attempt: True once a Cal1/Cal2 pair matches ``sent``. A mismatching pair ends
        the attempt early only when both lines are certainly newer than the store — printed
        after the sketch's "Wrote calibration" line, or received after more bytes than the OS
        can hold buffered (``BACKLOG_BYTES``); an older pair may still have been in the port's
        buffers when the packet went out. Otherwise the attempt runs to its timeout."""
        cal = {1: None, 2: None}
        fresh = {1: False, 2: False}
        rx0 = self.counters["bytes"]
        stored = False
        deadline = time.monotonic() + self.echo_timeout_s
        while time.monotonic() < deadline:
            for line in self._pull(min(0.05, max(0.0, deadline - time.monotonic()))):
                if isinstance(line, mc.OtherLine):
                    if line.note is mc.StoreNote.NOT_SAVED:
                        self._echo_stats[1] += 1
                    stored = stored or line.note is not None
                    continue
                if not isinstance(line, mc.CalLine):
                    continue
                cal[line.kind] = line
                fresh[line.kind] = stored or self.counters["bytes"] - rx0 > BACKLOG_BYTES
                if cal[1] is None or cal[2] is None:
                    continue
                self._echo_stats[0] += 1
                self._last_pair = (cal[1], cal[2])
                diff = mc.compare_echo(sent, cal[1], cal[2])
                if not diff:
                    echoed = mc.calibration_from_echo(cal[1], cal[2])
                    if echoed is not None:
                        self._echoed = echoed
                        self.counters["echo_verified"] += 1
                        return True
                self.last_echo_mismatch = diff
                if fresh[1] and fresh[2]:
                    return False
        return False

    def _send(self, packet: bytes) -> None:
        try:
            self._ser.write(packet)
            self._ser.flush()
        except Exception as exc:
            raise PortUnavailable(f"{self.url}: {exc}") from exc

    def _close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:
                pass
            self._ser = None


def accel_aux(line) -> dict:
    """The accelerometer a ``Raw:``/``Uni:`` line carries, in g, as a sample's ``ax_g, ay_g,
    az_g`` (which side of the board is down: ``magcal.logic.guidance``)."""
    if isinstance(line, mc.RawLine):
        a = [c * mc.G_PER_RAW_ACCEL for c in line.accel_counts]
    elif isinstance(line, mc.UniLine):
        a = [v / STANDARD_GRAVITY_MS2 for v in line.accel_ms2]
    else:
        return {}
    return dict(zip(("ax_g", "ay_g", "az_g"), map(float, a)))


STANDARD_GRAVITY_MS2 = 9.80665


def open_motioncal(port, dialect: Dialect = Dialect.MOTIONCAL, *, baud: int = 115200, tap=None, open_timeout_s: float = 3.0,
                   echo_timeout_s: float = 6.0, tries: int = 3, accel_offset=None, gyro_offset=None) -> Device:
    """A (not yet opened) MotionCalDevice on a serial port (``port``: a parsed port string)."""
    return MotionCalDevice(port.url, baud=baud, tap=tap, open_timeout_s=open_timeout_s, echo_timeout_s=echo_timeout_s,
                           tries=tries, accel_offset=accel_offset, gyro_offset=gyro_offset)
