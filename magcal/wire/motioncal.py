"""The PJRC MotionCal / Adafruit convention, pure: lines in, values out; packets out. No ports,
clocks or files (``parse_log`` takes a saved log's bytes; ``magcal.app.load`` reads the file).

Device → host, one text line per reading (we accept CR, LF or CRLF endings)::

    Raw:ax,ay,az,gx,gy,gz,mx,my,mz     9 integers: accel 1/8192 g, gyro 1/16 °/s, mag 0.1 µT
    Uni:ax,ay,az,gx,gy,gz,mx,my,mz     9 decimals (Adafruit sketches): accel m/s², gyro rad/s,
                                       mag µT (printed with 2 decimals, rounded)
    Cal1:a0,a1,a2,g0,g1,g2,v0,v1,v2,b  10 decimals: accel and gyro offsets, hard iron V (µT),
                                       field B (µT), printed with 3 decimals
    Cal2:w00,w01,...,w22               9 decimals: the soft-iron matrix, row-major, 4 decimals

Host → device, the 68-byte calibration packet (``encode_packet``): the signature 117, 84;
16 little-endian float32 — accel offset (3), gyro offset (3), hard iron V (3, µT), field B
(µT), invW00, invW11, invW22, invW01, invW02, invW12 — then CRC-16 (poly 0xA001 reflected, init
0xFFFF, i.e. CRC-16/MODBUS) over the first 66 bytes, low byte first. A receiver checks that the
CRC over all 68 bytes is 0. Sources: PJRC MotionCal (``send_calibration()``, the packet it sends);
Adafruit_AHRS ``examples/calibration/calibration.ino`` (``receiveCalibration``, the
``Cal1:``/``Cal2:`` prints) and Adafruit_Sensor_Calibration ``calibrate()``.

Soft iron. The device applies ``h = invW · (m − V)`` (Adafruit ``calibrate()``: subtract
``mag_hardiron``, multiply by ``mag_softiron``, which the sketch fills symmetrically from the
six invW numbers). magcal's ``Calibration`` corrects with ``h = soft_iron · (m − offset_ut)``,
so **the packet's invW is exactly ``Calibration.soft_iron``** (no inversion) and V is
``offset_ut``. ``Calibration.distort`` is the forward model ``m = soft_iron⁻¹ h + offset``;
``apply_like_device`` repeats the device's arithmetic so tests can round-trip the two.

Raw vs Uni. Adafruit sketches print ``Raw:`` with ``int(µT·10)`` — truncation toward zero,
a dead band of 0.1 µT around zero and a 0.05 µT shrink on average — and ``Uni:`` with the same
reading rounded to 0.01 µT. ``SampleAssembler`` therefore takes the field from ``Uni:`` while
a device sends them (one sample per reading, never two) and from ``Raw:`` otherwise.

Echo comparison (``compare_echo``): each echoed number is checked against what was sent at the
precision it was printed with — half a unit of its last printed digit, plus float32 rounding —
instead of MotionCal's fixed 1e-4 + 3e-5·|x|, which a 3-decimal echo of a small offset can fail.
"""

from __future__ import annotations

import re
import struct
from collections import Counter
from dataclasses import dataclass
from enum import Enum
from typing import Iterable, Sequence, Union

import numpy as np

from ..core.calibration import Calibration
from ..core.errors import InputError
from ..core.series import Series

SIGNATURE = bytes((117, 84))
PACKET_LEN = 68
PACKET_FLOATS = 16
UT_PER_RAW_COUNT = 0.1  # Raw: magnetometer counts
G_PER_RAW_ACCEL = 1.0 / 8192.0
DPS_PER_RAW_GYRO = 1.0 / 16.0
RAW_LIMIT = 32767  # MotionCal keeps Raw: values as int16
MAX_LINE = 200  # longer runs without an ending are noise
CAL1_DECIMALS = 3  # what the Adafruit / PJRC sketches print
CAL2_DECIMALS = 4
_F32_EPS = float(np.finfo(np.float32).eps)

TAGS = ("Raw:", "Uni:", "Cal1:", "Cal2:")
_INT = re.compile(r"[+-]?\d{1,6}\Z")
_FLOAT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)\Z")


# -- parsed lines (values) ----------------------------------------------------------------
@dataclass(frozen=True)
class RawLine:
    """``Raw:`` — integer counts; ``field_ut`` is the magnetometer in µT (counts × 0.1)."""

    accel_counts: tuple[int, int, int]
    gyro_counts: tuple[int, int, int]
    mag_counts: tuple[int, int, int]

    @property
    def field_ut(self) -> tuple[float, float, float]:
        return tuple(c * UT_PER_RAW_COUNT for c in self.mag_counts)


@dataclass(frozen=True)
class UniLine:
    """``Uni:`` — Adafruit unified units: accel m/s², gyro rad/s, field µT."""

    accel_ms2: tuple[float, float, float]
    gyro_rads: tuple[float, float, float]
    field_ut: tuple[float, float, float]


@dataclass(frozen=True)
class CalLine:
    """``Cal1:`` (kind 1, 10 numbers) or ``Cal2:`` (kind 2, 9 numbers) with the number of
    decimals each value was printed with (``nan``/``inf``/``ovf`` parse as nan, 0 decimals)."""

    kind: int
    values: tuple[float, ...]
    decimals: tuple[int, ...]


class StoreNote(Enum):
    """What a sketch says about the packet it was sent (Adafruit: "Wrote calibration",
    "Couldn't save calibration")."""

    WROTE = "wrote calibration"
    NOT_SAVED = "couldn't save calibration"


@dataclass(frozen=True)
class OtherLine:
    """Anything else: banners, ``Wrote calibration``, torn or noisy lines. ``reason`` says why
    a line that started with a known tag was not accepted ("" for plain text); ``note`` is the
    sketch's word on a packet, when the line is one."""

    text: str
    reason: str = ""

    @property
    def note(self) -> StoreNote | None:
        low = self.text.lower()
        return next((n for n in StoreNote if n.value in low), None)


Line = Union[RawLine, UniLine, CalLine, OtherLine]


def _decode(line) -> str:
    if isinstance(line, (bytes, bytearray)):
        return bytes(line).decode("latin-1")
    return str(line)


def find_tag(text: str) -> tuple[int, str]:
    """Position and name of the first known tag in ``text`` ((-1, "") when none)."""
    best = (-1, "")
    for tag in TAGS:
        i = text.find(tag)
        if i >= 0 and (best[0] < 0 or i < best[0]):
            best = (i, tag)
    return best


def _numbers(body: str, count: int, pattern) -> list[str] | None:
    parts = body.strip().split(",")
    if len(parts) != count or not all(pattern.match(p.strip()) for p in parts):
        return None
    return [p.strip() for p in parts]


def _float_token(tok: str) -> tuple[float, int] | None:
    t = tok.strip()
    if t.lower().lstrip("+-") in ("nan", "inf", "ovf"):
        return float("nan"), 0
    if not _FLOAT.match(t):
        return None
    return float(t), (len(t) - t.index(".") - 1) if "." in t else 0


def parse_line(line: str | bytes) -> Line:
    """One line (ending already removed, or not) → RawLine | UniLine | CalLine | OtherLine.

    Text before the first tag (line noise ahead of a line) is ignored; after the tag the line
    must be exactly right — a wrong count, a non-number or a Raw: value outside int16 makes it an
    ``OtherLine`` with a ``reason``, never a sample.

    >>> parse_line("Raw:0,0,8192,0,0,0,235,-412,128\\r").field_ut
    (23.5, -41.2, 12.8)
    """
    text = _decode(line).strip("\r\n")
    pos, tag = find_tag(text)
    if pos < 0:
        return OtherLine(text)
    body = text[pos + len(tag):]
    if tag == "Raw:":
        toks = _numbers(body, 9, _INT)
        if toks is None:
            return OtherLine(text, "malformed Raw:")
        v = [int(t) for t in toks]
        if any(abs(x) > RAW_LIMIT for x in v):
            return OtherLine(text, "Raw: value outside int16")
        return RawLine(tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9]))
    if tag == "Uni:":
        toks = _numbers(body, 9, _FLOAT)
        if toks is None:
            return OtherLine(text, "malformed Uni:")
        v = [float(t) for t in toks]
        return UniLine(tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9]))
    count = 10 if tag == "Cal1:" else 9
    parts = body.strip().split(",")
    parsed = [_float_token(p) for p in parts]
    if len(parts) != count or any(p is None for p in parsed):
        return OtherLine(text, f"malformed {tag}")
    # the sketches print every value of a Cal line with the same decimals: a last value with
    # fewer is a line that lost its tail (torn) and then met an ending — not an echo
    finite = [p[1] for p in parsed[:-1] if p[0] == p[0]]
    last_val, last_dec = parsed[-1]
    if finite and last_val == last_val and last_dec < max(finite):
        return OtherLine(text, f"malformed {tag} (torn: last value has fewer decimals)")
    return CalLine(1 if tag == "Cal1:" else 2, tuple(p[0] for p in parsed), tuple(p[1] for p in parsed))


# -- framing ------------------------------------------------------------------------------
class LineSplitter:
    """Bytes → complete lines, ending in CR, LF or CRLF (all three; empty lines vanish).

    A run longer than ``MAX_LINE`` without an ending is dropped and counted in
    ``counters["overlong"]`` (bounded memory). Pure: no I/O, feed it any chunking.
    """

    def __init__(self):
        self._buf = bytearray()
        self._skipping = False
        self.counters: Counter = Counter()

    def feed(self, data: bytes) -> list[bytes]:
        out = []
        for chunk in re.split(rb"([\r\n])", bytes(data)):
            if chunk in (b"\r", b"\n"):
                if self._skipping:
                    self._skipping = False
                elif self._buf:
                    out.append(bytes(self._buf))
                self._buf.clear()
            elif chunk and not self._skipping:
                self._buf += chunk
                if len(self._buf) > MAX_LINE:
                    self.counters["overlong"] += 1
                    self._buf.clear()
                    self._skipping = True
        return out


# -- readings → samples -------------------------------------------------------------------
class SampleAssembler:
    """Parsed lines → one magnetometer reading (µT) per device reading, plus counters.

    ``push(line)`` returns the field in µT when the line completes a reading, else None.
    Uni: lines win over Raw: lines while the device sends them (see the module docstring); a
    device that sends only one of the two works either way. Cal1:/Cal2: lines are remembered
    (``last_cal1``, ``last_cal2``) and counted, never turned into samples. Every line that is
    not a reading or a calibration echo is counted under ``junk`` (``malformed`` when it carried
    a known tag but was torn or corrupted).
    """

    def __init__(self):
        self.counters: Counter = Counter()
        self.uni_mode = False
        self._last_was_raw = False
        self._raw_since_uni = 0
        self.last_cal1: CalLine | None = None
        self.last_cal2: CalLine | None = None

    def push(self, line: Line) -> tuple[float, float, float] | None:
        c = self.counters
        c["lines"] += 1
        if isinstance(line, RawLine):
            c["raw"] += 1
            self._raw_since_uni += 1
            if self.uni_mode and self._raw_since_uni <= 2:
                self._last_was_raw = True
                return None  # its Uni: twin carries the same reading with more resolution
            self.uni_mode = False
            self._last_was_raw = True
            return line.field_ut
        if isinstance(line, UniLine):
            c["uni"] += 1
            self._raw_since_uni = 0
            paired = self._last_was_raw
            self._last_was_raw = False
            if not self.uni_mode:
                self.uni_mode = True
                if paired:
                    return None  # the Raw: just before already gave this reading
            return line.field_ut
        self._last_was_raw = False
        if isinstance(line, CalLine):
            c[f"cal{line.kind}"] += 1
            if line.kind == 1:
                self.last_cal1 = line
            else:
                self.last_cal2 = line
            return None
        c["junk"] += 1
        if line.reason:
            c["malformed"] += 1
        return None


# -- the calibration packet ---------------------------------------------------------------
def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16 poly 0xA001 (reflected 0x8005), init 0xFFFF: crc16(b"123456789") == 0x4B37."""
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def packet_values(
    cal: Calibration,
    accel_offset: Sequence[float] = (0.0, 0.0, 0.0),
    gyro_offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[float, ...]:
    """The 16 numbers of the packet, in packet order, as float64 (before float32 rounding).

    Raises ValueError for a calibration the packet cannot carry (temperature, current or time
    terms: the convention has no place for them) — silently dropping them would store a
    different model from the one that was fitted.
    """
    extra = [k for k, v in cal.coef_ut_per_unit.items() if np.any(v)]
    if extra:
        raise ValueError(
            "the MotionCal packet carries only hard iron, soft iron and field; this calibration "
            f"also has {', '.join(sorted(extra))} terms"
        )
    w = cal.soft_iron
    vals = [*map(float, accel_offset), *map(float, gyro_offset), *map(float, cal.offset_ut),
            float(cal.field_ut), w[0, 0], w[1, 1], w[2, 2], w[0, 1], w[0, 2], w[1, 2]]
    if len(vals) != PACKET_FLOATS or not all(np.isfinite(vals)):
        raise ValueError("accel and gyro offsets must be 3 finite numbers each")
    return tuple(float(v) for v in vals)


def encode_packet(
    cal: Calibration,
    accel_offset: Sequence[float] = (0.0, 0.0, 0.0),
    gyro_offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> bytes:
    """The 68-byte packet for ``cal`` (accel/gyro offsets in the device's units; Adafruit:
    m/s² and rad/s, zeros mean "none"). ``crc16(packet) == 0``."""
    body = SIGNATURE + struct.pack("<16f", *packet_values(cal, accel_offset, gyro_offset))
    crc = crc16(body)
    return body + bytes((crc & 0xFF, crc >> 8))


def decode_packet(packet: bytes) -> tuple[float, ...]:
    """68 bytes → the 16 floats; ValueError naming the problem (length, signature, CRC)."""
    packet = bytes(packet)
    if len(packet) != PACKET_LEN:
        raise ValueError(f"a calibration packet is {PACKET_LEN} bytes, got {len(packet)}")
    if packet[:2] != SIGNATURE:
        raise ValueError(f"packet signature is {packet[0]}, {packet[1]}, expected 117, 84")
    if crc16(packet) != 0:
        raise ValueError("packet CRC-16 does not check")
    return struct.unpack("<16f", packet[2:66])


def soft_iron_from_packet(values: Sequence[float]) -> np.ndarray:
    """The symmetric 3×3 the device builds from packet floats 10…15 (as Adafruit does)."""
    d0, d1, d2, o01, o02, o12 = (float(v) for v in values[10:16])
    return np.array([[d0, o01, o02], [o01, d1, o12], [o02, o12, d2]])


def calibration_from_packet(values: Sequence[float]) -> Calibration:
    return Calibration(offset_ut=values[6:9], field_ut=values[9], soft_iron=soft_iron_from_packet(values))


def apply_like_device(values: Sequence[float], m_ut) -> np.ndarray:
    """What an Adafruit device computes from packet floats: invW · (m − V), (n, 3) µT."""
    m = np.atleast_2d(np.asarray(m_ut, dtype=np.float64))
    return (m - np.asarray(values[6:9], dtype=np.float64)) @ soft_iron_from_packet(values).T


# -- the echo -----------------------------------------------------------------------------
def echo_values(cal1: CalLine, cal2: CalLine) -> tuple[tuple[float, ...], tuple[int, ...]]:
    """Cal1 + Cal2 → the 16 packet-ordered values and the decimals each was printed with."""
    a = cal2.values
    d = cal2.decimals
    # Cal2 is the full matrix row-major: 00 01 02 / 10 11 12 / 20 21 22
    order = (0, 4, 8, 1, 2, 5)
    vals = tuple(cal1.values) + tuple(a[i] for i in order)
    decs = tuple(cal1.decimals) + tuple(d[i] for i in order)
    return vals, decs


def calibration_from_echo(cal1: CalLine, cal2: CalLine) -> Calibration | None:
    """The calibration the device says it holds, or None when the echo is not a usable model
    (nan, a soft iron that is not symmetric positive definite)."""
    if cal1.kind != 1 or cal2.kind != 2:
        raise ValueError("calibration_from_echo takes a Cal1 line and a Cal2 line")
    w = np.array(cal2.values, dtype=np.float64).reshape(3, 3)
    tol = 10.0 ** -min(cal2.decimals) if min(cal2.decimals) > 0 else 1.0
    if not np.all(np.isfinite(w)) or np.any(np.abs(w - w.T) > tol):
        return None
    try:
        return Calibration(offset_ut=cal1.values[6:9], field_ut=cal1.values[9], soft_iron=w)
    except ValueError:
        return None


PACKET_NAMES = (
    "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z",
    "hard_iron_x", "hard_iron_y", "hard_iron_z", "field",
    "invW00", "invW11", "invW22", "invW01", "invW02", "invW12",
)


def echo_tolerance(sent: float, decimals: int) -> float:
    """How far an echo printed with ``decimals`` decimals may lie from ``sent``: half a unit of
    the last printed digit, plus a few float32 ulps (the device stores float32 and prints with
    float arithmetic)."""
    return 0.5 * 10.0 ** -decimals + 8 * _F32_EPS * max(1.0, abs(sent))


def compare_echo(sent: Sequence[float], cal1: CalLine, cal2: CalLine) -> list[str]:
    """Differences between the 16 sent packet values and an echo, at the echo's printed
    precision; empty when the echo confirms the packet. Each entry reads like
    ``"hard_iron_x: sent 23.5, echo 23.600 (±0.0005)"``."""
    vals, decs = echo_values(cal1, cal2)
    out = []
    # the off-diagonal terms appear twice in Cal2: both copies must agree with what was sent
    w = np.array(cal2.values).reshape(3, 3)
    dw = np.array(cal2.decimals).reshape(3, 3)
    twins = {13: (1, 0), 14: (2, 0), 15: (2, 1)}
    for i, (s, e, d) in enumerate(zip(sent, vals, decs)):
        checks = [(e, d)]
        if i in twins:
            checks.append((float(w[twins[i]]), int(dw[twins[i]])))
        for ev, dv in checks:
            tol = echo_tolerance(s, dv)
            if not (abs(ev - s) <= tol):  # nan fails
                out.append(f"{PACKET_NAMES[i]}: sent {s:.6g}, echo {ev:.{dv}f} (±{tol:.2g})")
    return out


def compare_tolerance(decimals_ut: int = CAL1_DECIMALS, decimals_w: int = CAL2_DECIMALS) -> dict:
    """Keyword arguments for ``Calibration.close_to`` that accept an echo printed with the
    given decimals (µT values and soft-iron terms) and nothing looser."""
    return {
        "atol_ut": 0.5 * 10.0 ** -decimals_ut + 8 * _F32_EPS * 2000.0,
        "atol_w": 0.5 * 10.0 ** -decimals_w + 8 * _F32_EPS * 10.0,
    }


# -- auto-detection and offline logs ------------------------------------------------------
def looks_like_motioncal(first_lines: Iterable[str | bytes]) -> bool:
    """True when the first lines of a port or file are in the MotionCal convention: at least
    one well-formed ``Raw:`` or ``Uni:`` line, and more of them than native-protocol lines
    (``$T,…*CC``)."""
    ours = native = 0
    for line in first_lines:
        text = _decode(line).strip("\r\n")
        if isinstance(parse_line(text), (RawLine, UniLine)):
            ours += 1
        elif re.search(r"\$[A-Z],.*\*[0-9A-F]{2}\s*\Z", text):
            native += 1
    return ours > 0 and ours > native


def parse_log(data: bytes, rate_hz: float | None = None, source: str = "log") -> Series:
    """A saved MotionCal-style log (bytes) → Series of the magnetometer in µT.

    The convention carries no time: ``t_s`` is the sample index divided by ``rate_hz``, and
    with ``rate_hz=None`` simply the sample index (an assumed 1 Hz) — only the order of
    samples is real. ``row`` maps each sample to its 0-based line in the file. Raises
    InputError when no Raw:/Uni: line is found.
    """
    asm = SampleAssembler()
    fields, rows = [], []
    for i, line in enumerate(bytes(data).splitlines()):  # CR, LF and CRLF alike
        if not line.strip():
            continue
        f = asm.push(parse_line(line))
        if f is not None:
            fields.append(f)
            rows.append(i)
    if not fields:
        raise InputError(
            f"{source}: no Raw: or Uni: lines found ({asm.counters['lines']} lines read); "
            "not a MotionCal-style log"
        )
    if rate_hz is not None and not (rate_hz > 0):
        raise InputError(f"{source}: rate_hz must be positive, got {rate_hz}")
    n = len(fields)
    t = np.arange(n, dtype=np.float64) / (1.0 if rate_hz is None else float(rate_hz))
    return Series(t_s=t, field_ut=np.array(fields), row=np.array(rows), clock=rate_hz is not None)
