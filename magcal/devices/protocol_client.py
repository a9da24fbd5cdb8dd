"""The host side of wire protocol v1 over any byte transport: ``ProtocolDevice``.

A transport is anything shaped like a pyserial port: ``read(n) -> bytes`` (returns early, possibly
empty, after ``timeout`` seconds), ``write(data)``, ``in_waiting``, a settable ``timeout``, and
``close()``. Serial ports, pyserial URLs (``socket://``, ``loop://`` …), the emulated board's pty,
the ``sim://`` board and ``replay://`` captures are all transports, so this one class is the
protocol client for all of them. The device is given a *connector* (called with no arguments,
it returns an open transport): ``open`` calls it, and calls it again after ``close`` — that is
how a link reconnects to the same board.

Nothing that arrives is dropped: samples that come in while a command waits for its reply are
queued and returned by the next ``read``.
"""

from __future__ import annotations

import itertools
import time
from collections import Counter, deque
from dataclasses import replace
from typing import Callable, Iterable

from ..core.calibration import Calibration, RecordState, StoredRecord
from ..core.errors import CommandRefused, DeviceError, IdentityError, NoReply, PortUnavailable, WriteRejected
from ..core.chips import MPU9150, Chip, chip_from_ids
from ..core.sample import Sample, counts_to_ut, temp_raw_to_c
from ..core.selftest import SelfTestResult
from ..wire.dialect import Dialect
from ..wire.protocol import (
    ACCEL_COUNTS_PER_G,
    PROTO_VERSION,
    Ack,
    CalibratedSample,
    ErrorReply,
    FitReply,
    Framer,
    Gap,
    Hello,
    Log,
    Measurement,
    RawSample,
    RecordReply,
    Restart,
    calibration_from_record,
    encode_command,
    hello_applies,
    quantize_calibration,
    record_crc,
    record_from_calibration,
    stored_record,
)
from .base import RECORDING, Abilities, Device, Event, Identity, Item
from .port import Port
from .transport import Connector, SerialPort, tapped

# defects of lines the framer dropped, any of which may have been a reply being waited for
DROPPED = ("overlong_lines", "torn_lines", "bad_checksums", "malformed_lines", "bad_syntax", "unknown_types")
WHO_AM_I_MPU9150 = 0x68
WIA_AK8975 = 0x48


def hello_chip(hello: Hello | None) -> Chip | None:
    """The part a hello names by its ids and resolution (``bits``; 0 or absent: by the ids)."""
    if hello is None:
        return None
    try:
        return chip_from_ids(hello.who_am_i, hello.wia, getattr(hello, "bits", None) or None)
    except ValueError:
        return None


class Inbox:
    """What arrives on one connection, sorted: samples and link events for ``read`` (in order),
    replies for the command waiting on them, and the device's clock turned into seconds that
    keep rising across restarts. ``counters``: the device's (resets and log lines go there)."""

    def __init__(self, counters, fallback_asa: Callable[[], tuple[int, int, int]]):
        self.framer = Framer()
        self.pending: deque[Item] = deque()
        self.replies: deque = deque()
        self.hello: Hello | None = None
        self.expect_restart = False  # a reset was asked for: its hello is no fault
        self.rate_set_hz: int | None = None  # the rate the last R reply on the link confirmed
        self._counters = counters
        self._fallback_asa = fallback_asa
        self._ms_last: int | None = None
        self._t_offset_s = 0.0
        self._t_last_s = 0.0

    def feed(self, data: bytes) -> None:
        for item in self.framer.feed(data):
            self._sort(item)

    def take(self) -> list[Item]:
        out = list(self.pending)
        self.pending.clear()
        return out

    def forget_replies(self) -> None:
        """Replies nobody waits for any more (a command that timed out, a hello already used)."""
        self.replies.clear()

    def reply(self, pred):
        """The first reply ``pred`` accepts, taken out of the queue; None when none has come."""
        for i, r in enumerate(self.replies):
            if pred(r):
                del self.replies[i]
                return r
        return None

    def _sort(self, item) -> None:
        if isinstance(item, RawSample):
            self.pending.append(self._sample(item))
        elif isinstance(item, CalibratedSample):
            chip = hello_chip(self.hello) or MPU9150
            self.pending.append(Sample(seq=item.seq, t_s=self._time(item.ms),
                                       field_ut=tuple(v / 1000.0 for v in item.field_nt), st2=item.st2,
                                       temp_c=temp_raw_to_c(item.temp_raw, chip),
                                       aux={"calibrated": 1.0, **accel_aux(item, chip)}, chip=chip))
        elif isinstance(item, Gap):
            self.pending.append(Event("gap", seq=item.seq, count=item.count))
        elif isinstance(item, Restart):
            if self.expect_restart:
                self.expect_restart = False
            else:
                self._counters["device_resets"] += 1
                self.pending.append(Event("reset", seq=item.seq, detail="unsolicited hello"))
            self._new_epoch()
        elif isinstance(item, Hello):
            if not hello_applies(self.hello, item):
                self._counters["hellos_refused"] += 1  # a changed identity without a restart
                return
            self.hello = item
            if item.seq == 0 and self.expect_restart:
                self.expect_restart = False
                self._new_epoch()
            self.replies.append(item)
        elif isinstance(item, Log):
            self._counters["log_lines"] += 1
        else:  # Ack, ErrorReply, RecordReply, FitReply
            if isinstance(item, Ack) and item.cmd == "R" and item.result and item.result[0].isdigit():
                self.rate_set_hz = int(item.result[0])
            self.replies.append(item)

    def _new_epoch(self) -> None:
        self._t_offset_s = self._t_last_s
        self._ms_last = None

    def _time(self, ms: int) -> float:
        if self._ms_last is not None:
            t = self._t_last_s + ((ms - self._ms_last) % (1 << 32)) / 1000.0
        else:
            t = self._t_offset_s + ms / 1000.0
        self._ms_last = ms
        self._t_last_s = t
        return t

    def _sample(self, s: RawSample) -> Sample:
        # the latest hello describes the chip that sent this sample (so a replay does not
        # depend on how its bytes were chunked); before any hello, the identity or unity gain
        asa = self.hello.asa if self.hello else self._fallback_asa()
        chip = hello_chip(self.hello) or MPU9150
        field = counts_to_ut(s.raw, asa) * (chip.ut_per_count / MPU9150.ut_per_count)
        return Sample(seq=s.seq, t_s=self._time(s.ms), field_ut=(float(field[0]), float(field[1]), float(field[2])),
                      raw=s.raw, st2=s.st2, temp_c=temp_raw_to_c(s.temp_raw, chip), chip=chip, aux=accel_aux(s, chip))


def accel_aux(m: Measurement, chip: Chip) -> dict:
    """The accelerometer a sample line carries, in g, as a sample's ``ax_g, ay_g, az_g`` (which
    side of the board is down: ``magcal.logic.guidance``); nothing from a board that sends none.
    The line carries the IMU's registers in the IMU's own axes; the sample's three are turned
    into the magnetometer's axes (``chip.mag_from_accel``), the frame of its ``field_ut``."""
    if m.accel is None:
        return {}
    a = chip.accel_to_mag(m.accel) / ACCEL_COUNTS_PER_G
    return {name: float(v) for name, v in zip(("ax_g", "ay_g", "az_g"), a)}



class ProtocolDevice(Device):
    """Protocol v1 client. ``passive=True`` only listens (replay): it never writes."""

    abilities = Abilities(live=True, store=True, self_test=True)

    def __init__(
        self,
        url: str,
        connect: Connector,
        *,
        transport_name: str = "serial",
        passive: bool = False,
        reply_timeout_s: float = 1.5,
        boot_timeout_s: float = 3.0,
        clock: Callable[[], float] = time.monotonic,
        initial: bytes = b"",
        tap: Callable | None = None,
    ):
        super().__init__(url, clock)
        self._connect = connect
        self._tap = tap  # a capture writer that records every byte read (``transport.tapped``)
        self.transport = None
        self.transport_name = transport_name
        self.passive = passive
        if passive:
            self.abilities = RECORDING
        self.reply_timeout_s = reply_timeout_s
        self.boot_timeout_s = boot_timeout_s
        self.record_status: str | None = None  # last record status seen: OK, BLANK, CORRUPT
        self.last_fit: FitReply | None = None
        self._tags = itertools.cycle(range(1, 65536))
        self._initial = initial  # bytes a detection already read from the first connection
        self.link_totals: Counter = Counter()  # the framer counts of the connections before this one
        self.inbox: Inbox | None = None
        self._new_link()

    @classmethod
    def over(cls, url: str, transport, **options) -> "ProtocolDevice":
        """The client on one already-open transport (a recording in memory, a test's port)."""
        return cls(url, lambda: transport, **options)

    def _new_link(self) -> None:
        """Forget what the previous connection said: a new connection starts from nothing (its
        framer's counts are kept in ``link_totals``, so ``stats`` counts over every connection)."""
        if self.inbox is not None:
            self.link_totals += self.inbox.framer.counters
        self.inbox = Inbox(self.counters, lambda: self.identity.asa if self.identity else (128, 128, 128))
        self._eof = False

    @property
    def framer(self) -> Framer:
        return self.inbox.framer

    # -- low level -------------------------------------------------------------------------
    def _pump(self, timeout_s: float) -> bool:
        """Read what the transport has (waiting at most ``timeout_s``); False if nothing."""
        lost = None
        try:
            self.transport.timeout = max(0.0, timeout_s)
            waiting = self.transport.in_waiting or 0
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
            self.inbox.feed(data)
        if lost is not None:
            raise PortUnavailable(f"{self.url}: port lost ({lost})") from lost
        return bool(data)

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

    def _await(self, pred, what: str, timeout_s: float | None = None, overlong_ends: bool = False):
        deadline = self.clock() + (self.reply_timeout_s if timeout_s is None else timeout_s)
        before = Counter(self.framer.counters)
        while True:
            r = self.inbox.reply(pred)
            if r is not None:
                return r
            left = deadline - self.clock()
            # overlong_ends: a line too long for any reply ends the wait (``_stored_record_of``)
            overlong = overlong_ends and self.framer.counters["overlong_lines"] > before["overlong_lines"]
            if left <= 0 or self._eof or overlong:
                self.counters["no_reply"] += 1
                seen = self.framer.counters - before  # what the link dropped meanwhile may be the reply
                bad = ", ".join(f"{seen[k]} {k.replace('_', ' ')}" for k in DROPPED if seen[k])
                raise _no_reply(f"{self.url}: no {what} within {timeout_s or self.reply_timeout_s:.1f} s"
                                + (f" (meanwhile the link dropped {bad})" if bad else ""), seen)
            self._pump(min(left, 0.05))

    def command(self, cmd: str, *args, timeout_s: float | None = None) -> Ack:
        """Send a command and return its acknowledgement; an error reply raises DeviceError."""
        tag = self._send(cmd, *args)
        r = self._await(
            lambda r: isinstance(r, (Ack, ErrorReply)) and r.tag == tag, f"reply to {cmd}", timeout_s
        )
        if isinstance(r, ErrorReply):
            raise CommandRefused(f"{self.url}: device refused {cmd}: {r.code}", cmd, r.code)
        return r

    # -- Device hooks ----------------------------------------------------------------------
    def _open(self) -> Identity:
        self._new_link()
        self.transport = tapped(self._connect(), self._tap)
        initial, self._initial = self._initial, b""
        self.inbox.feed(initial)
        if self.passive:
            return self._identity_passive()
        # A board that was just reset (DTR) may lose the first I while it boots: its boot
        # hello says it now listens, and the I is asked again at once. Identified = answers I.
        deadline = self.clock() + self.boot_timeout_s
        hello = None
        while hello is None and self.clock() < deadline:
            try:
                tag = self._send("I")
                if _boot_hello(self._await(lambda r: _boot_hello(r) or _acks(r, tag), "reply to I", 0.6)):
                    tag = self._send("I")
                    self._await(lambda r: _acks(r, tag), "reply to I", 0.6)
                hello = self._await(lambda r: isinstance(r, Hello) and not _boot_hello(r), "hello", 0.6)
            except NoReply:
                self.inbox.forget_replies()
        if hello is None:
            seen = ", ".join(f"{k}={v}" for k, v in sorted(self.framer.counters.items())) or "nothing"
            raise NoReply(f"{self.url}: the device did not identify within {self.boot_timeout_s:.0f} s "
                          f"(is it running magcal firmware at this baud rate? link saw: {seen})")
        self.inbox.forget_replies()
        return self._identity_from(hello)

    def _identity_from(self, hello: Hello) -> Identity:
        if hello.proto != PROTO_VERSION:
            raise IdentityError(f"{self.url}: device speaks protocol {hello.proto}, this host speaks {PROTO_VERSION}")
        if hello_chip(hello) is None:
            _refuse_ids(self.url, hello)
        return Identity(
            transport=self.transport_name,
            proto=hello.proto,
            firmware=hello.firmware,
            who_am_i=hello.who_am_i,
            wia=hello.wia,
            asa=hello.asa,
            rate_hz=hello.rate_hz,
            bits=hello_chip(hello).bits,
        )

    def _identity_passive(self) -> Identity:
        # Listen until the recording's hello; samples before it are kept for read().
        while self.inbox.hello is None and not self._eof:
            if not self._pump(0.05) and self._eof:
                break
            if len(self.inbox.pending) > 1000:
                break
        self.inbox.forget_replies()
        if self.inbox.hello is None:
            return Identity(transport=self.transport_name, firmware="unknown")
        return self._identity_from(self.inbox.hello)

    def _start(self, rate_hz: int | None) -> None:
        if self.passive:
            _rate_from_stream(self)
            return
        if rate_hz:
            self.command("R", int(rate_hz))
            if self.identity is not None:  # what the device now runs at, for reports
                self.identity = replace(self.identity, rate_hz=int(rate_hz))
        self.command("G")

    def _stop(self) -> None:
        if not self.passive:
            self.command("X")

    def _receive(self, wait_s: float) -> Iterable[Item]:
        if not self.inbox.pending:
            if self._eof:
                raise EOFError(self.url)
            try:
                self._pump(min(max(0.0, wait_s), 0.1))
            except PortUnavailable:
                if not self.inbox.pending:
                    raise
                # hand over what arrived first; the next read finds the port gone
        return self.inbox.take()

    def set_output(self, calibrated: bool) -> None:
        self.command("M", 1 if calibrated else 0)

    def reset(self) -> Identity:
        """Ask the board to restart; returns its new identity (not reported as a fault)."""
        self.inbox.expect_restart = True
        self.command("Z")
        self.framer.reset_sequence()
        hello = self._await(_boot_hello, "hello after reset", self.boot_timeout_s)
        self.identity = self._identity_from(hello)
        return self.identity

    def read_record(self) -> RecordReply:
        tag = self._send("K")
        r = self._await(
            lambda r: isinstance(r, (RecordReply, ErrorReply)) and r.tag == tag, "calibration record", overlong_ends=True
        )
        if isinstance(r, ErrorReply):
            raise CommandRefused(f"{self.url}: device refused K: {r.code}", "K", r.code)
        self.record_status = r.status
        return r

    def prepare(self, cal: Calibration) -> Calibration:
        return quantize_calibration(cal)

    def matches(self, sent: Calibration, stored: Calibration | None) -> bool:
        # v1 records are integers: what was sent must come back bit for bit.
        return stored is not None and record_from_calibration(sent) == record_from_calibration(stored)

    def stored_in(self) -> str | None:
        """A simulated board's EEPROM file on this host (sim://, emu://); None for a real board."""
        board = getattr(self, "board", None)
        path = getattr(board, "eeprom_path", None) or getattr(getattr(board, "eeprom", None), "path", None)
        return str(path) if path else None

    def _read_calibration(self) -> Calibration | None:
        return self._read_stored().calibration

    def _read_stored(self) -> StoredRecord:
        return _stored_record_of(self)

    def _judge_record(self, r: RecordReply) -> StoredRecord:
        stored = stored_record(r.status, r.values, r.crc)
        if stored.state is RecordState.CORRUPT and r.status == "OK":
            self.record_status = "CORRUPT"
            self.counters["record_crc_errors"] += 1
        elif stored.state is RecordState.INVALID:
            self.record_status = "INVALID"
            self.counters["record_invalid"] += 1
        return stored

    def _discard_calibration(self) -> StoredRecord:
        r = _record_after(self, self._send("D"), "D")
        if isinstance(r, ErrorReply):
            raise CommandRefused(f"{self.url}: device refused D: {r.code}" + (
                " (its firmware cannot discard a record: flash the current sketch from firmware/)"
                if r.code == "UNKNOWN" else ""), "D", r.code)
        return self._judge_record(r)

    def _write_calibration(self, cal: Calibration) -> Calibration:
        values = record_from_calibration(cal)
        crc = record_crc(values)
        r = _record_after(self, self._send("W", *values, f"{crc:04X}"), "W")
        if isinstance(r, ErrorReply):
            raise WriteRejected(f"{self.url}: device rejected the calibration: {r.code}")
        stored = self._judge_record(r)
        if stored.calibration is None:
            raise WriteRejected(f"{self.url}: after W the device holds no calibration: "
                                f"{stored.problem or stored.state.value}")
        return stored.calibration

    def _self_test(self) -> SelfTestResult:
        """The AK8975 self-test on the board (``T``): the coil's raw reading, judged here
        against the datasheet window with the ASA bytes of the board's hello."""
        try:
            ack = self.command("T")
        except CommandRefused as exc:
            if exc.code == "UNKNOWN":
                raise DeviceError(f"{self.url}: this firmware has no self-test command (T); flash the current "
                                  "sketch from firmware/") from None
            raise
        ident = self.identity
        result = _self_test_result(self.url, ack, ident.asa if ident else (128, 128, 128), (ident and ident.chip) or MPU9150)
        self.counters["self_test_pass" if result.passed else "self_test_fail"] += 1
        return result

    def standalone_fit(self, n: int, naive: bool = False, timeout_s: float = 60.0) -> FitReply:
        """Ask the board to collect ``n`` samples and solve the sphere fit itself."""
        ack = self.command("N" if naive else "F", int(n))
        r = self._await(lambda r: isinstance(r, FitReply) and r.tag == ack.tag, "standalone fit result", timeout_s)
        self.last_fit = r
        return r

    def stats(self) -> dict:
        """The framer's counters (lines, defects, gaps) over every connection so far, and the
        client's (bytes, commands …)."""
        return {**(self.link_totals + self.framer.counters), **self.counters}

    def _close(self) -> None:
        if self.transport is not None:
            self.transport.close()


def _record_after(dev: ProtocolDevice, tag: int, cmd: str) -> ErrorReply | RecordReply:
    """The device's answer to a store command (W, D): its refusal, or the record it now holds."""
    r = dev._await(lambda r: isinstance(r, (Ack, ErrorReply)) and r.tag == tag, f"reply to {cmd}")
    if isinstance(r, ErrorReply):
        return r
    rec = dev._await(lambda r: isinstance(r, RecordReply) and r.tag == tag, f"stored record after {cmd}")
    dev.record_status = rec.status
    return rec


def _self_test_result(url: str, ack: Ack, asa, chip: Chip = MPU9150) -> SelfTestResult:
    """The self-test reply (T: raw x, y, z, ST2) judged against the datasheet window."""
    try:
        raw, st2 = tuple(int(v) for v in ack.result[:3]), int(ack.result[3])
    except (ValueError, IndexError):
        raise DeviceError(f"{url}: malformed self-test reply {','.join(ack.result)!r}") from None
    return SelfTestResult.from_registers(raw, asa, st2, window=chip.self_test_window)


def _acks(r, tag: int) -> bool:
    return isinstance(r, Ack) and r.tag == tag


def _boot_hello(r) -> bool:
    """A board's boot message (its hello with seq 0), as opposed to a hello replying to ``I``."""
    return isinstance(r, Hello) and r.seq == 0


def _refuse_ids(url: str, hello: Hello) -> None:
    """IdentityError naming the id no supported part has."""
    if hello.who_am_i == WHO_AM_I_MPU9150:
        raise IdentityError(f"{url}: AK8975 WIA is 0x{hello.wia:02X}, expected 0x48")
    raise IdentityError(f"{url}: WHO_AM_I 0x{hello.who_am_i:02X} with magnetometer id 0x{hello.wia:02X} "
                        "is no supported chip (expected 0x68 (MPU-9150), 0x71/0x73 with 0x48 "
                        "(MPU-9250/9255) or 0xEA with 0x09 (ICM-20948))")


def _no_reply(message: str, dropped: Counter) -> NoReply:
    """NoReply, with what the link dropped meanwhile (a caller may blame that instead)."""
    err = NoReply(message)
    err.dropped = dropped
    return err


def _stored_record_of(device: ProtocolDevice) -> StoredRecord:
    """What the device's store holds (``K``). A reply longer than a protocol line can be (the
    link drops it) is the record's fault, not a silent device's: it holds values no calibration
    has (int32 extremes) — an INVALID record, replaced by the next write. One overlong line may
    be noise; the same twice is the reply."""
    for _ in range(2):
        try:
            return device._judge_record(device.read_record())
        except NoReply as exc:
            if not getattr(exc, "dropped", {}).get("overlong_lines"):
                raise
    device.record_status = "INVALID"
    device.counters["record_invalid"] += 1
    return StoredRecord(RecordState.INVALID, problem="the device's record reply was longer than a protocol "
                        "line (120 bytes): its record holds values no calibration has")


def _rate_from_stream(dev: "ProtocolDevice") -> None:
    """A recording runs at the rate its device was set to (the R reply it carries, read up to
    its first sample), not at the hello's boot rate nor at one asked for now."""
    for _ in range(40):
        if dev.inbox.pending or dev._eof:
            break
        dev._pump(0.05)
    if dev.inbox.rate_set_hz and dev.identity is not None:
        dev.identity = replace(dev.identity, rate_hz=dev.inbox.rate_set_hz)


def open_serial(port: Port, dialect: Dialect = Dialect.NATIVE, *, baud: int = 115200, tap=None,
                reply_timeout_s: float = 1.5, boot_timeout_s: float = 3.0, open_timeout_s: float = 3.0,
                echo_timeout_s: float = 6.0, tries: int = 3) -> Device:
    """A serial port or pyserial URL speaking protocol v1 (or, with ``Dialect.AUTO``, whichever
    of v1 and the MotionCal convention the first lines show: ``open_timeout_s``,
    ``echo_timeout_s`` and ``tries`` are that client's options, for when it is the one)."""
    url = port.url
    v1 = dict(transport_name="serial", tap=tap, reply_timeout_s=reply_timeout_s, boot_timeout_s=boot_timeout_s)
    connector = SerialPort(url, baud)
    if dialect is not Dialect.AUTO:
        return ProtocolDevice(url, connector, **v1)
    from .autodetect import detect_dialect

    first = connector()
    # a capture records from the first byte, the detection's included
    dialect, seen = detect_dialect(tapped(first, tap))
    if dialect is Dialect.MOTIONCAL:
        from .motioncal_client import MotionCalDevice

        first.close()
        return MotionCalDevice(url, baud=baud, tap=tap, open_timeout_s=open_timeout_s,
                               echo_timeout_s=echo_timeout_s, tries=tries)
    return ProtocolDevice(url, SerialPort(url, baud, first=first), initial=seen, **v1)
