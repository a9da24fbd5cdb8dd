"""Wire protocol v1 (``docs/protocol.md``): pure framing, parsing and encoding.

No I/O here. ``Framer.feed(data)`` takes any chunk of bytes — torn lines, noise, over-long runs,
bad checksums — and returns the messages it completed plus link events (sequence gaps, device
restarts). Nothing malformed is ever raised out of the stream or merged into data: it is
counted in ``Framer.counters``.

Calibration records travel as 18 fixed-point integers (see the spec); ``record_from_calibration``
and ``calibration_from_record`` convert, ``record_crc`` protects them.
"""

from __future__ import annotations

import struct
from collections import Counter
from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np

from ..core.calibration import Calibration, RecordState, StoredRecord
from ..core.sense import record_problem

PROTO_VERSION = 1
MAX_LINE = 120  # bytes including '$' and '\n'
SEQ_MOD = 65536
RECORD_VERSION = 1
RECORD_FIELDS = 18  # v, ox, oy, oz, r, w00, w11, w22, w01, w02, w12, tx, ty, tz, tref, ix, iy, iz
ACCEL_COUNTS_PER_G = 16384  # the samples' accelerometer fields: an MPU's ACCEL_*OUT registers at ±2 g
TOO_LONG = "TOO_LONG"  # a C reply cut at MAX_LINE: the record's values are too long to be a calibration's


# -- checksums ----------------------------------------------------------------------------
def _crc8_table() -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)
    return table


CRC8_TABLE = _crc8_table()
CRC8_TABLE_NP = np.array(CRC8_TABLE, dtype=np.uint8)


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS (poly 0x07, init 0). crc8(b"123456789") == 0xF4."""
    c = 0
    t = CRC8_TABLE
    for b in data:
        c = t[c ^ b]
    return c


def crc16_ccitt(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF). crc16_ccitt(b"123456789") == 0x29B1."""
    c = 0xFFFF
    for b in data:
        c ^= b << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) & 0xFFFF if c & 0x8000 else (c << 1) & 0xFFFF
    return c


# -- messages -----------------------------------------------------------------------------
HELLO_BITS = (13, 14, 16)  # the magnetometer resolutions a hello may state (0: no magnetometer)


@dataclass(frozen=True, slots=True)
class Hello:
    """``H``: who the device is (also its boot message: seq 0).

    ``bits`` is the trailing field a multi-chip device adds: the magnetometer's output
    resolution (13 AK8975, 14 or 16 AK8963, 16 AK09916; 0 when none answered), None from a
    device that does not state it (an MPU-9150 board: 13). Fields after it are ignored."""

    seq: int
    proto: int
    firmware: str
    who_am_i: int
    wia: int
    asa: tuple[int, int, int]
    rate_hz: int
    bits: int | None = None


@dataclass(frozen=True, slots=True)
class Measurement:
    """A measurement line: device ``millis()`` at the trigger, three values, ST2, TEMP_OUT and the
    accelerometer's registers (``ACCEL_COUNTS_PER_G``; None from a board that sends none)."""

    seq: int
    ms: int
    values: tuple[int, int, int]
    st2: int
    temp_raw: int
    accel: tuple[int, int, int] | None = None


@dataclass(frozen=True, slots=True)
class RawSample(Measurement):
    """``S``: the AK8975 data registers as signed counts, not ASA-adjusted."""

    @property
    def raw(self) -> tuple[int, int, int]:
        return self.values


@dataclass(frozen=True, slots=True)
class CalibratedSample(Measurement):
    """``U`` (output mode 1): the field with the stored calibration applied, in nT."""

    @property
    def field_nt(self) -> tuple[int, int, int]:
        return self.values


@dataclass(frozen=True, slots=True)
class Reply:
    """An answer to the host command that carried ``tag``."""

    seq: int
    tag: int


@dataclass(frozen=True, slots=True)
class Ack(Reply):
    """``A``: command ``cmd`` done; any result fields follow."""

    cmd: str
    result: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class ErrorReply(Reply):
    """``E``: command ``cmd`` refused, with an error code (``RANGE``, ``UNKNOWN`` …)."""

    cmd: str
    code: str


@dataclass(frozen=True, slots=True)
class RecordReply(Reply):
    """``C``: the stored calibration record (the reply to ``K``, and to ``W`` after storing)."""

    status: str  # OK, BLANK, CORRUPT; TOO_LONG: the reply was cut at the line limit (values no record has)
    values: tuple[int, ...]  # the 18 record integers
    crc: int


@dataclass(frozen=True, slots=True)
class FitReply(Reply):
    """``F``: the board's own sphere fit: offset and radius in nT, the pivot ratio × 1000."""

    n: int
    offset_nt: tuple[int, int, int]
    radius_nt: int
    cond_milli: int


@dataclass(frozen=True, slots=True)
class Log:
    """``L``: free text from the device (counted, ignored)."""

    seq: int
    text: str


@dataclass(frozen=True, slots=True)
class Gap:
    """``count`` device lines were lost just before the line with ``seq``."""

    seq: int
    count: int


@dataclass(frozen=True, slots=True)
class Restart:
    """The device restarted (a hello with seq 0 that does not continue the numbering)."""

    seq: int


Message = Union[Hello, RawSample, CalibratedSample, Ack, ErrorReply, RecordReply, FitReply, Log]
Frame = Union[Message, Gap, Restart]  # what the framer yields: a message, or a gap or restart it saw


class ParseError(ValueError):
    pass


class UnknownMessage(ParseError):
    """A well-framed line of a type this host does not know (a newer firmware's)."""


def _int(tok: bytes) -> int:
    # int() accepts '_' and surrounding spaces; the protocol does not.
    if not tok or not (tok.isdigit() or (tok[:1] in (b"-", b"+") and tok[1:].isdigit())):
        raise ParseError(f"not a decimal integer: {tok!r}")
    return int(tok)


def _hex(tok: bytes) -> int:
    if not tok or len(tok) > 4 or any(c not in b"0123456789ABCDEF" for c in tok):
        raise ParseError(f"not upper-case hex: {tok!r}")
    return int(tok, 16)


def _ints(toks: Sequence[bytes]) -> tuple[int, ...]:
    return tuple(_int(t) for t in toks)


def _need(toks, n, what):
    if len(toks) != n:
        raise ParseError(f"{what} needs {n} fields, got {len(toks)}")


def _measurement_fields(f: Sequence[bytes], kind: bytes) -> Sequence[bytes]:
    """The six fields of every ``S``/``U`` line; the accelerometer's three (then any) may follow."""
    if len(f) < 6 or len(f) in (7, 8):
        raise ParseError(f"{kind.decode()} needs 6 fields, or 9 with the accelerometer's, got {len(f)}")
    return f[:6]


def parse_payload(payload: bytes) -> Message:
    """Parse the bytes between '$' and '*' (checksum already verified)."""
    toks = payload.split(b",")
    if len(toks) < 2 or len(toks[0]) != 1:
        raise ParseError("missing type or sequence number")
    kind = toks[0]
    seq = _int(toks[1])
    if not 0 <= seq < SEQ_MOD:
        raise ParseError(f"sequence number out of range: {seq}")
    f = toks[2:]
    if kind in (b"S", b"U"):
        ms, x, y, z, st2, temp = _ints(_measurement_fields(f, kind))
        accel = _ints(f[6:9]) if len(f) >= 9 else None
        return (RawSample if kind == b"S" else CalibratedSample)(seq, ms, (x, y, z), st2, temp, accel)
    if kind == b"H":
        if len(f) < 8:
            raise ParseError(f"H needs at least 8 fields, got {len(f)}")
        fw = f[1].decode("ascii")
        if not fw or any(c not in "0123456789." for c in fw):
            raise ParseError(f"bad firmware version {fw!r}")
        asa = _ints(f[4:7])
        if not all(0 <= a <= 255 for a in asa):
            raise ParseError(f"ASA bytes out of range: {asa}")
        who, wia = _hex(f[2]), _hex(f[3])
        if who > 255 or wia > 255:
            raise ParseError("WHO_AM_I and WIA are single bytes")
        bits = _int(f[8]) if len(f) > 8 else None
        if bits is not None and bits not in (0, *HELLO_BITS):
            raise ParseError(f"magnetometer resolution {bits} bits is none of 13, 14, 16 (or 0)")
        return Hello(seq, _int(f[0]), fw, who, wia, asa, _int(f[7]), bits)
    if kind == b"A":
        if len(f) < 2:
            raise ParseError("A needs tag and command")
        return Ack(seq, _int(f[0]), f[1].decode("ascii"), tuple(x.decode("ascii") for x in f[2:]))
    if kind == b"E":
        _need(f, 3, "E")
        return ErrorReply(seq, _int(f[0]), f[1].decode("ascii"), f[2].decode("ascii"))
    if kind == b"C":
        if len(f) < 2 + RECORD_FIELDS + 1 and len(payload) >= MAX_LINE - 16 and len(f) >= 2:
            # a sketch cuts a reply at the line limit: a record whose values do not fit is no
            # calibration (int32 extremes), and is said as such, not taken for silence
            return RecordReply(seq, _int(f[0]), TOO_LONG, (), 0)
        _need(f, 2 + RECORD_FIELDS + 1, "C")
        status = f[1].decode("ascii")
        if status not in ("OK", "BLANK", "CORRUPT"):
            raise ParseError(f"bad record status {status!r}")
        return RecordReply(seq, _int(f[0]), status, _ints(f[2 : 2 + RECORD_FIELDS]), _hex(f[-1]))
    if kind == b"F":
        _need(f, 7, "F")
        v = _ints(f)
        return FitReply(seq, v[0], v[1], v[2:5], v[5], v[6])
    if kind == b"L":
        return Log(seq, b",".join(f).decode("ascii", "replace"))
    raise UnknownMessage(f"unknown message type {kind!r}")


def _printable(b: bytes) -> bool:
    return all(32 <= c < 127 for c in b)


_HEX = b"0123456789ABCDEFabcdef"


def classify_line(line: bytes) -> Message | str:
    """One complete candidate line (from its '$' up to, not including, the '\\n') → the
    message it carries, or the name of the counter its defect goes to: ``malformed_lines``
    (not ``$…*CC`` printable ASCII), ``bad_checksums`` (CRC mismatch or lower-case hex),
    ``unknown_types`` or ``bad_syntax``. Pure; the one line judge for every framer."""
    if line.endswith(b"\r"):
        line = line[:-1]
    star = line.rfind(b"*")
    if not line.startswith(b"$") or star < 0 or len(line) - star != 3 or not _printable(line):
        return "malformed_lines"
    cc = line[star + 1 :]
    if cc[0] not in _HEX or cc[1] not in _HEX:
        return "malformed_lines"
    payload = line[1:star]
    if cc.upper() != cc or crc8(payload) != int(cc, 16):
        return "bad_checksums"
    try:
        return parse_payload(payload)
    except UnknownMessage:
        return "unknown_types"
    except (ParseError, UnicodeDecodeError):
        return "bad_syntax"


def hello_applies(current: Hello | None, new: Hello) -> bool:
    """Does ``new`` describe the chip that sends the samples after it? The first hello and a
    boot hello (seq 0) do. A later one (the reply to ``I``) must repeat the chip's identity —
    WHO_AM_I, WIA and the fuse-ROM ASA bytes cannot change without a restart — so one that does
    not is refused (and counted by the reader as ``hellos_refused``): a changed ASA in a line
    whose CRC-8 happened to match would otherwise rescale every later sample. The resolution
    (``bits``) is part of that identity."""
    if current is None or new.seq == 0:
        return True
    return (new.who_am_i, new.wia, new.asa, new.bits) == (current.who_am_i, current.wia, current.asa, current.bits)


MAX_MISORDER = 100  # a line this far behind the last one is a late copy, not news
MAX_DROPOUT = 3000  # a jump further ahead than this is implausible as loss (30 s at 100 Hz)


class SequenceTracker:
    """Sequence-number bookkeeping shared by every framer: which lines continue the stream,
    gaps, device restarts. The rules follow RFC 3550, appendix A.1 (RTP's sequence check):

    - a hello with seq 0 that does not continue the numbering is a device restart;
    - 1 … ``MAX_DROPOUT`` ahead of the last line continues the stream; the numbers skipped
      are ``lost_lines`` (one ``gap`` per jump);
    - the same number again, or up to ``MAX_MISORDER`` behind, is a copy that came late or
      twice: ``duplicate_lines``, never delivered (a sample is never counted twice);
    - any other jump is ``out_of_sequence_lines`` (not delivered) unless the next line
      follows it: then the device has renumbered without a hello (``sequence_resyncs``),
      delivered as a restart so the time axis starts a new epoch.
    """

    def __init__(self):
        self.last: int | None = None
        self._probation: int | None = None  # the number that would confirm a renumbering

    def step(self, msg: Message, counters: Counter, out: list) -> bool:
        """Judge ``msg``; True when it continues the stream (deliver it), False when not."""
        last, seq = self.last, msg.seq
        if isinstance(msg, Hello) and seq == 0 and last != SEQ_MOD - 1:
            self.last, self._probation = 0, None
            if last is not None:
                counters["restarts"] += 1
                out.append(Restart(0))
            return True
        if last is None:
            self.last = seq
            return True
        ahead = (seq - last) % SEQ_MOD
        if ahead == 0 or ahead > SEQ_MOD - MAX_MISORDER:
            counters["duplicate_lines"] += 1
            return False
        if ahead <= MAX_DROPOUT:
            self.last, self._probation = seq, None
            if ahead > 1:
                counters["lost_lines"] += ahead - 1
                counters["gaps"] += 1
                out.append(Gap(seq, ahead - 1))
            return True
        if seq == self._probation:  # two in a row on a new numbering
            self.last, self._probation = seq, None
            counters["sequence_resyncs"] += 1
            out.append(Restart(seq))
            return True
        self._probation = (seq + 1) % SEQ_MOD
        counters["out_of_sequence_lines"] += 1
        return False


def _next_stop(buf: bytes, i: int) -> int:
    """Index of the next '$' or '\\n' at or after ``i`` (``len(buf)`` when neither)."""
    d = buf.find(b"$", i)
    n = buf.find(b"\n", i)
    if d < 0:
        return len(buf) if n < 0 else n
    return d if n < 0 or d < n else n


class Framer:
    """Bytes in, messages and link events out. Bounded memory: at most MAX_LINE bytes held.

    The result does not depend on how the stream is split into chunks: feeding a stream whole
    or byte by byte gives the same items and the same counters. Rules (docs/protocol.md, "Lines"):
    every '$' starts a line; a line is complete at '\\n'. Counted, never raised:

    - ``noise_bytes``: every byte not inside a complete line (bytes outside lines, torn and
      over-long runs with their ending), except the unfinished line still held;
    - ``torn_lines``: a '$' run cut short by the next '$';
    - ``overlong_lines``: a '$' run that reaches MAX_LINE bytes without a '\\n' (dropped
      until the next '\\n' or '$');
    - per complete line, see ``classify_line``; ``lines`` counts the good ones;
    - ``gaps``/``lost_lines``/``restarts``, ``duplicate_lines``, ``out_of_sequence_lines`` and
      ``sequence_resyncs`` from the sequence numbers (``SequenceTracker``); duplicates and
      out-of-sequence lines are not returned.
    """

    def __init__(self):
        self.counters: Counter = Counter()
        self._carry = b""  # the start of an unfinished line, beginning with '$'
        self._skipping = False  # inside an over-long run: drop until the next '\n' or '$'
        self._seq = SequenceTracker()

    def reset_sequence(self) -> None:
        """Forget the last sequence number (after the host itself reset the device)."""
        self._seq.last = None

    def feed(self, data: bytes) -> list[Frame]:
        out: list[Frame] = []
        buf = bytes(data)
        n = len(buf)
        c = self.counters
        i = 0
        while i < n:
            if self._skipping:
                j = _next_stop(buf, i)
                if j == n:
                    c["noise_bytes"] += n - i
                    break
                self._skipping = False
                if buf[j] == 0x0A:
                    c["noise_bytes"] += j - i + 1
                    i = j + 1
                else:  # a '$' ends the over-long run and starts a new line
                    c["noise_bytes"] += j - i
                    i = j
                continue
            if not self._carry:
                j = buf.find(b"$", i)
                if j < 0:
                    c["noise_bytes"] += n - i
                    break
                c["noise_bytes"] += j - i
                self._carry = b"$"
                i = j + 1
                continue
            j = _next_stop(buf, i)
            if len(self._carry) + (j - i) >= MAX_LINE:  # cannot end within MAX_LINE bytes
                c["overlong_lines"] += 1
                c["noise_bytes"] += len(self._carry)
                self._carry = b""
                self._skipping = True
            elif j == n:
                self._carry += buf[i:]
                break
            elif buf[j] == 0x24:  # '$': this line was torn
                c["torn_lines"] += 1
                c["noise_bytes"] += len(self._carry) + (j - i)
                self._carry = b""
                i = j
            else:
                line = self._carry + buf[i:j]
                self._carry = b""
                i = j + 1
                self._line(line, out)
        return out

    def _line(self, line: bytes, out: list) -> None:
        msg = classify_line(line)
        if isinstance(msg, str):
            self.counters[msg] += 1
            return
        if self._seq.step(msg, self.counters, out):
            out.append(msg)
            self.counters["lines"] += 1


def parse_command(line: bytes) -> tuple[str, int, tuple[bytes, ...]]:
    """A host command line (device side): (letter, tag, raw argument tokens).

    Raises ParseError with one of the protocol's error codes as its message: CRC, SYNTAX, LONG."""
    line = line.rstrip(b"\r\n")
    if len(line) + 1 > MAX_LINE:
        raise ParseError("LONG")
    star = line.rfind(b"*")
    if not line.startswith(b"$") or star < 0 or len(line) - star != 3:
        raise ParseError("SYNTAX")
    payload = line[1:star]
    try:
        want = int(line[star + 1 :], 16)
    except ValueError:
        raise ParseError("SYNTAX") from None
    if crc8(payload) != want:
        raise ParseError("CRC")
    toks = payload.split(b",")
    if len(toks) < 2 or len(toks[0]) != 1:
        raise ParseError("SYNTAX")
    try:
        tag = _int(toks[1])
    except ParseError:
        raise ParseError("SYNTAX") from None
    return toks[0].decode("ascii", "replace"), tag, tuple(toks[2:])


# -- encoding -----------------------------------------------------------------------------
def encode_line(kind: str, fields: Sequence) -> bytes:
    payload = ",".join([kind, *(str(f) for f in fields)]).encode("ascii")
    return b"$" + payload + b"*" + f"{crc8(payload):02X}".encode("ascii") + b"\n"


def encode_command(cmd: str, tag: int, *args) -> bytes:
    if not 1 <= tag < SEQ_MOD:
        raise ValueError(f"command tag out of range: {tag}")
    return encode_line(cmd, (tag, *args))


# -- calibration records ------------------------------------------------------------------
def record_crc(values: Sequence[int]) -> int:
    if len(values) != RECORD_FIELDS:
        raise ValueError(f"a record has {RECORD_FIELDS} values, got {len(values)}")
    return crc16_ccitt(struct.pack("<18i", *values))


def _nt(x_ut: float) -> int:
    return int(round(float(x_ut) * 1000.0))


def record_from_calibration(cal: Calibration) -> tuple[int, ...]:
    """Calibration → the 18 fixed-point integers of a v1 record (nT, 1e-6, nT/°C, 0.01 °C, nT/A).

    Only ``temp_c`` and ``current_a`` channel terms fit in a v1 record; others raise."""
    extra = set(cal.coef_ut_per_unit) - {"temp_c", "current_a"}
    if extra:
        raise ValueError(f"a v1 record cannot carry channel terms {sorted(extra)}")
    w = cal.soft_iron
    t = cal.coef_ut_per_unit.get("temp_c", np.zeros(3))
    i = cal.coef_ut_per_unit.get("current_a", np.zeros(3))
    if cal.reference.get("current_a", 0.0) != 0.0:
        raise ValueError("a v1 record takes the current reference at 0 A")
    values = (
        RECORD_VERSION,
        *(_nt(v) for v in cal.offset_ut),
        _nt(cal.field_ut),
        *(int(round(w[a, b] * 1e6)) for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))),
        *(_nt(v) for v in t),
        int(round(cal.reference.get("temp_c", 0.0) * 100.0)),
        *(_nt(v) for v in i),
    )
    for v in values:
        if not -(2**31) <= v < 2**31:
            raise ValueError("calibration value out of range for a v1 record")
    return values


def calibration_from_record(values: Sequence[int]) -> Calibration:
    if len(values) != RECORD_FIELDS or values[0] != RECORD_VERSION:
        raise ValueError("not a v1 calibration record")
    v = [float(x) for x in values]
    w00, w11, w22, w01, w02, w12 = (x / 1e6 for x in v[5:11])
    coef, ref = {}, {}
    if any(v[11:14]):
        coef["temp_c"] = [x / 1000.0 for x in v[11:14]]
        ref["temp_c"] = v[14] / 100.0
    if any(v[15:18]):
        coef["current_a"] = [x / 1000.0 for x in v[15:18]]
    return Calibration(
        offset_ut=[x / 1000.0 for x in v[1:4]],
        field_ut=v[4] / 1000.0,
        soft_iron=[[w00, w01, w02], [w01, w11, w12], [w02, w12, w22]],
        coef_ut_per_unit=coef,
        reference=ref,
    )


def stored_record(status: str, values: Sequence[int], crc: int) -> StoredRecord:
    """A ``C`` line's record → what the store holds: blank, corrupt (as the device or the CRC
    says), invalid (the record checks out but is no calibration), or the calibration (pure)."""
    if status == "BLANK":
        return StoredRecord(RecordState.NONE)
    if status == TOO_LONG:
        return StoredRecord(RecordState.INVALID, problem="the device's record reply was cut at the protocol's line "
                            f"limit ({MAX_LINE} bytes): its record holds values no calibration has")
    if status != "OK":
        return StoredRecord(RecordState.CORRUPT, problem=f"the device reports its record as {status} "
                            "(format, version or CRC wrong)")
    if record_crc(values) != crc:
        return StoredRecord(RecordState.CORRUPT, problem="the record's CRC does not match its values")
    try:
        cal = calibration_from_record(values)
    except ValueError as exc:
        return StoredRecord(RecordState.INVALID, problem=f"the record passes its CRC but is no calibration: {exc}")
    nonsense = record_problem(cal)  # CRC-valid, and still no physical calibration (core.sense)
    if nonsense:
        return StoredRecord(RecordState.INVALID, problem=f"the record passes its CRC but is no calibration: {nonsense}")
    return StoredRecord(RecordState.OK, cal)


def quantize_calibration(cal: Calibration) -> Calibration:
    """The calibration exactly as a v1 record will carry it."""
    return calibration_from_record(record_from_calibration(cal))
