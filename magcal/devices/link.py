"""The host side of wire protocol v1 over any byte transport: ``ProtocolDevice``.

A transport is anything shaped like a pyserial port: ``read(n) -> bytes`` (returns early, possibly
empty, after ``timeout`` seconds), ``write(data)``, ``in_waiting``, a settable ``timeout``, and
``close()``. Serial ports, pyserial URLs (``socket://``, ``loop://`` …), the emulated board's pty,
the ``sim://`` board and ``replay://`` captures are all transports, so this one class is the
protocol client for all of them.

Nothing that arrives is dropped: samples that come in while a command waits for its reply are
queued and returned by the next ``read``.
"""

from __future__ import annotations

import itertools
import time
from collections import deque
from dataclasses import replace
from typing import Callable, Iterable

from ..core.calibration import Calibration
from ..core.errors import DeviceError, IdentityError, NoReply, PortUnavailable, WriteRejected
from ..core.sample import Sample, counts_to_ut, temp_raw_to_c
from ..core.selftest import SelfTestResult
from ..wire.protocol import (
    PROTO_VERSION,
    Ack,
    CalibratedSample,
    ErrorReply,
    FitReply,
    Framer,
    Gap,
    Hello,
    Log,
    RawSample,
    RecordReply,
    Restart,
    calibration_from_record,
    encode_command,
    quantize_calibration,
    record_crc,
    record_from_calibration,
)
from .base import Device, Event, Identity, Item
from .transport import tapped

WHO_AM_I_MPU9150 = 0x68
WIA_AK8975 = 0x48


class ProtocolDevice(Device):
    """Protocol v1 client. ``passive=True`` only listens (replay): it never writes."""

    def __init__(
        self,
        url: str,
        transport,
        *,
        transport_name: str = "serial",
        on_close: Callable[[], None] | None = None,
        passive: bool = False,
        reply_timeout_s: float = 1.5,
        boot_timeout_s: float = 3.0,
        clock: Callable[[], float] = time.monotonic,
        initial: bytes = b"",
        tap: Callable | None = None,
    ):
        super().__init__(url)
        # ``tap``: a capture writer that records every byte read (``transport.tapped``)
        self.transport = tapped(transport, tap)
        self.transport_name = transport_name
        self.passive = passive
        self.can_store = not passive
        self.reply_timeout_s = reply_timeout_s
        self.boot_timeout_s = boot_timeout_s
        self.framer = Framer()
        self.record_status: str | None = None  # last record status seen: OK, BLANK, CORRUPT
        self.last_fit: FitReply | None = None
        self._on_close = on_close
        self._clock = clock
        self._tags = itertools.cycle(range(1, 65536))
        self._pending: deque[Item] = deque()
        self._replies: deque = deque()
        self._expect_restart = False
        self._hello: Hello | None = None
        self._ms_last: int | None = None
        self._t_offset_s = 0.0
        self._t_last_s = 0.0
        self._eof = False
        for item in self.framer.feed(initial):
            self._dispatch(item)

    # -- low level -------------------------------------------------------------------------
    def _pump(self, timeout_s: float) -> bool:
        """Read what the transport has (waiting at most ``timeout_s``); False if nothing."""
        lost = None
        try:
            self.transport.timeout = max(0.0, timeout_s)
            waiting = getattr(self.transport, "in_waiting", 0) or 0
            data = self.transport.read(max(1, min(waiting, 65536)))
            try:
                if data and self.transport.in_waiting:
                    data += self.transport.read(self.transport.in_waiting)
            except (OSError, ValueError) as exc:  # keep what was read before the port went
                lost = exc
        except EOFError:
            self._eof = True
            return False
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise PortUnavailable(f"{self.url}: port lost ({exc})") from exc
        if data:
            self.counters["bytes_in"] += len(data)
            for item in self.framer.feed(data):
                self._dispatch(item)
        if lost is not None:
            raise PortUnavailable(f"{self.url}: port lost ({lost})") from lost
        return bool(data)

    def _dispatch(self, item) -> None:
        if isinstance(item, RawSample):
            self._pending.append(self._sample(item))
        elif isinstance(item, CalibratedSample):
            t = self._time(item.ms)
            self._pending.append(
                Sample(
                    seq=item.seq,
                    t_s=t,
                    field_ut=tuple(v / 1000.0 for v in item.field_nt),
                    st2=item.st2,
                    temp_c=temp_raw_to_c(item.temp_raw),
                    aux={"calibrated": 1.0},
                )
            )
        elif isinstance(item, Gap):
            self._pending.append(Event("gap", seq=item.seq, count=item.count))
        elif isinstance(item, Restart):
            if self._expect_restart:
                self._expect_restart = False
            else:
                self.counters["device_resets"] += 1
                self._pending.append(Event("reset", seq=item.seq, detail="unsolicited hello"))
            self._new_epoch()
        elif isinstance(item, Hello):
            self._hello = item
            if item.seq == 0 and self._expect_restart:
                self._expect_restart = False
                self._new_epoch()
            self._replies.append(item)
        elif isinstance(item, Log):
            self.counters["log_lines"] += 1
        else:  # Ack, ErrorReply, RecordReply, FitReply
            self._replies.append(item)

    def _new_epoch(self) -> None:
        self._t_offset_s = self._t_last_s
        self._ms_last = None

    def _time(self, ms: int) -> float:
        if self._ms_last is not None:
            step = (ms - self._ms_last) % (1 << 32)
            t = self._t_last_s + step / 1000.0
        else:
            t = self._t_offset_s + ms / 1000.0
        self._ms_last = ms
        self._t_last_s = t
        return t

    def _sample(self, s: RawSample) -> Sample:
        # the latest hello describes the chip that sent this sample (so a replay does not
        # depend on how its bytes were chunked); before any hello, the identity or unity gain
        asa = self._hello.asa if self._hello else (self.identity.asa if self.identity else (128,) * 3)
        field = counts_to_ut(s.raw, asa)
        return Sample(
            seq=s.seq,
            t_s=self._time(s.ms),
            field_ut=(float(field[0]), float(field[1]), float(field[2])),
            raw=s.raw,
            st2=s.st2,
            temp_c=temp_raw_to_c(s.temp_raw),
        )

    def _send(self, cmd: str, *args) -> int:
        if self.passive:
            raise DeviceError(f"{self.url}: a replay cannot take commands")
        tag = next(self._tags)
        try:
            self.transport.write(encode_command(cmd, tag, *args))
        except (OSError, ValueError) as exc:
            raise PortUnavailable(f"{self.url}: port lost while writing ({exc})") from exc
        self.counters["commands"] += 1
        return tag

    def _await(self, pred, what: str, timeout_s: float | None = None):
        deadline = self._clock() + (self.reply_timeout_s if timeout_s is None else timeout_s)
        while True:
            for i, r in enumerate(self._replies):
                if pred(r):
                    del self._replies[i]
                    return r
            left = deadline - self._clock()
            if left <= 0 or self._eof:
                self.counters["no_reply"] += 1
                raise NoReply(f"{self.url}: no {what} within {timeout_s or self.reply_timeout_s:.1f} s")
            self._pump(min(left, 0.05))

    def command(self, cmd: str, *args, timeout_s: float | None = None) -> Ack:
        """Send a command and return its acknowledgement; an error reply raises DeviceError."""
        tag = self._send(cmd, *args)
        r = self._await(
            lambda r: isinstance(r, (Ack, ErrorReply)) and r.tag == tag, f"reply to {cmd}", timeout_s
        )
        if isinstance(r, ErrorReply):
            raise DeviceError(f"{self.url}: device refused {cmd}: {r.code}")
        return r

    # -- Device hooks ----------------------------------------------------------------------
    def _open(self) -> Identity:
        if self.passive:
            return self._identity_passive()
        # A board that was just reset (DTR) sends its boot hello first; otherwise ask.
        deadline = self._clock() + self.boot_timeout_s
        hello = None
        while hello is None and self._clock() < deadline:
            try:
                tag = self._send("I")
                self._await(lambda r: isinstance(r, Ack) and r.tag == tag, "reply to I", 0.6)
                hello = self._await(lambda r: isinstance(r, Hello), "hello", 0.6)
            except NoReply:
                self._replies.clear()
                continue
        if hello is None:
            seen = ", ".join(f"{k}={v}" for k, v in sorted(self.framer.counters.items())) or "nothing"
            raise NoReply(
                f"{self.url}: the device did not identify within {self.boot_timeout_s:.0f} s "
                f"(is it running magcal firmware at this baud rate? link saw: {seen})"
            )
        self._replies.clear()
        return self._identity_from(hello)

    def _identity_from(self, hello: Hello) -> Identity:
        if hello.proto != PROTO_VERSION:
            raise IdentityError(f"{self.url}: device speaks protocol {hello.proto}, this host speaks {PROTO_VERSION}")
        if hello.who_am_i != WHO_AM_I_MPU9150:
            raise IdentityError(f"{self.url}: WHO_AM_I is 0x{hello.who_am_i:02X}, expected 0x68 (MPU-9150)")
        if hello.wia != WIA_AK8975:
            raise IdentityError(f"{self.url}: AK8975 WIA is 0x{hello.wia:02X}, expected 0x48")
        return Identity(
            transport=self.transport_name,
            proto=hello.proto,
            firmware=hello.firmware,
            who_am_i=hello.who_am_i,
            wia=hello.wia,
            asa=hello.asa,
            rate_hz=hello.rate_hz,
        )

    def _identity_passive(self) -> Identity:
        # Listen until the recording's hello; samples before it are kept for read().
        while self._hello is None and not self._eof:
            if not self._pump(0.05) and self._eof:
                break
            if len(self._pending) > 1000:
                break
        self._replies.clear()
        if self._hello is None:
            return Identity(transport=self.transport_name, firmware="unknown")
        return self._identity_from(self._hello)

    def _start(self, rate_hz: int | None) -> None:
        if self.passive:
            return
        if rate_hz:
            self.command("R", int(rate_hz))
            if self.identity is not None:  # what the device now runs at, for reports
                self.identity = replace(self.identity, rate_hz=int(rate_hz))
        self.command("G")

    def _stop(self) -> None:
        if not self.passive:
            self.command("X")

    def _read(self, timeout_s: float) -> Iterable[Item]:
        if not self._pending:
            if self._eof:
                raise EOFError(self.url)
            deadline = self._clock() + timeout_s
            while not self._pending and not self._eof:
                left = deadline - self._clock()
                if left <= 0:
                    break
                try:
                    self._pump(min(left, 0.1))
                except PortUnavailable:
                    if not self._pending:
                        raise
                    break  # hand over what arrived first; the next read finds the port gone
        out = list(self._pending)
        self._pending.clear()
        return out

    def set_output(self, calibrated: bool) -> None:
        self.command("M", 1 if calibrated else 0)

    def reset(self) -> Identity:
        """Ask the board to restart; returns its new identity (not reported as a fault)."""
        self._expect_restart = True
        self.command("Z")
        self.framer.reset_sequence()
        hello = self._await(lambda r: isinstance(r, Hello), "hello after reset", self.boot_timeout_s)
        self.identity = self._identity_from(hello)
        return self.identity

    def read_record(self) -> RecordReply:
        tag = self._send("K")
        r = self._await(
            lambda r: isinstance(r, (RecordReply, ErrorReply)) and r.tag == tag, "calibration record"
        )
        if isinstance(r, ErrorReply):
            raise DeviceError(f"{self.url}: device refused K: {r.code}")
        self.record_status = r.status
        return r

    def prepare(self, cal: Calibration) -> Calibration:
        return quantize_calibration(cal)

    def matches(self, sent: Calibration, stored: Calibration | None) -> bool:
        # v1 records are integers: what was sent must come back bit for bit.
        return stored is not None and record_from_calibration(sent) == record_from_calibration(stored)

    def _read_calibration(self) -> Calibration | None:
        r = self.read_record()
        if r.status != "OK":
            return None
        if record_crc(r.values) != r.crc:
            self.record_status = "CORRUPT"
            self.counters["record_crc_errors"] += 1
            return None
        return calibration_from_record(r.values)

    def _write_calibration(self, cal: Calibration) -> Calibration:
        values = record_from_calibration(cal)
        crc = record_crc(values)
        tag = self._send("W", *values, f"{crc:04X}")
        r = self._await(lambda r: isinstance(r, (Ack, ErrorReply)) and r.tag == tag, "reply to W")
        if isinstance(r, ErrorReply):
            raise WriteRejected(f"{self.url}: device rejected the calibration: {r.code}")
        rec = self._await(lambda r: isinstance(r, RecordReply) and r.tag == tag, "stored record after W")
        self.record_status = rec.status
        if rec.status != "OK" or record_crc(rec.values) != rec.crc:
            raise WriteRejected(f"{self.url}: device reports its stored record as {rec.status} after W")
        return calibration_from_record(rec.values)

    def self_test(self) -> SelfTestResult:
        """The AK8975 self-test on the board (``T``): the coil's raw reading, judged here
        against the datasheet window with the ASA bytes of the board's hello."""
        try:
            ack = self.command("T")
        except DeviceError as exc:
            if "UNKNOWN" in str(exc):
                raise DeviceError(f"{self.url}: this firmware has no self-test command (T); flash the current "
                                  "sketch from firmware/") from None
            raise
        try:
            raw, st2 = tuple(int(v) for v in ack.result[:3]), int(ack.result[3])
        except (ValueError, IndexError):
            raise DeviceError(f"{self.url}: malformed self-test reply {','.join(ack.result)!r}") from None
        result = SelfTestResult.from_registers(raw, self.identity.asa if self.identity else (128, 128, 128), st2)
        self.counters["self_test_pass" if result.passed else "self_test_fail"] += 1
        return result

    def standalone_fit(self, n: int, naive: bool = False, timeout_s: float = 60.0) -> FitReply:
        """Ask the board to collect ``n`` samples and solve the sphere fit itself."""
        ack = self.command("N" if naive else "F", int(n))
        r = self._await(lambda r: isinstance(r, FitReply) and r.tag == ack.tag, "standalone fit result", timeout_s)
        self.last_fit = r
        return r

    def _close(self) -> None:
        try:
            self.transport.close()
        finally:
            if self._on_close:
                self._on_close()


def open_serial(url: str, dialect: str = "native", baud: int = 115200, **options) -> Device:
    """A serial port or pyserial URL speaking protocol v1 (or, with ``dialect='auto'``, whichever
    of v1 and the MotionCal convention the first lines show)."""
    import serial  # pyserial

    try:
        port = serial.serial_for_url(url, baudrate=baud, timeout=0.05)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise PortUnavailable(f"cannot open {url}: {exc}") from exc
    tap = options.pop("tap", None)
    if tap is not None:  # a capture records from the first byte, the detection's included
        port = tapped(port, tap)
    if dialect == "auto":
        from .autodetect import detect_dialect

        dialect, seen = detect_dialect(port)
        if dialect == "motioncal":
            from .motioncal import open_motioncal

            port.close()
            if tap is not None:
                options["tap"] = tap
            return open_motioncal(url, dialect="motioncal", baud=baud, **options)
        return ProtocolDevice(url, port, transport_name="serial", initial=seen, **options)
    return ProtocolDevice(url, port, transport_name="serial", **options)
