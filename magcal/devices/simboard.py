"""``sim://`` — a pure-Python simulated board that speaks protocol v1 as bytes.

It is a *transport*: the host's real protocol client (``ProtocolDevice``) talks to it exactly as
it talks to a serial port, so every layer above runs unchanged. Its sensor readings come from
the one physics simulator (``magcal.sim.physics``); its EEPROM persists to a file when given one.

Options (the port string's, ``magcal.devices.port``): ``seed``, ``rate`` (initial rate, default
100), ``pace`` (1 = real time, the default, as a board would; N = N× real time; 0 = as fast as
the host reads, for quick trials, tests and benchmarks: ``sim://?pace=0``),
``eeprom`` (a file kept across runs; by default one per seed in the user's state directory,
as for ``emu://``; ``eeprom=none`` for a throwaway one), ``motion``, ``offset``, ``noise``, ``field``, ``accel`` (``off``: samples without the
accelerometer's three trailing fields, as from a board that has none) and ``fault`` — every fault of
``magcal.devices.faults`` but the register-model ones, fired when the board's physics time
reaches it. Board flags can also be set directly in ``SimBoard.faults`` (``mute``,
``no_write_ack``, ``corrupt_write``).

The device that ``open_device`` builds keeps its board (``dev.board``) for its whole life:
opening it again after a close — or after an unplug — reconnects to the same board, with the
same EEPROM, physics time and pending faults, as replugging a real board would. A board made
beforehand can be handed in as ``open_device(url, board=SimBoard(...))``.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections import Counter
from dataclasses import replace

import numpy as np

from ..core.errors import PortUnavailable
from ..core.chips import MPU9150, NEUTRAL_ASA
from ..core.sample import counts_to_ut, temp_raw_to_c
from ..recordings.atomic import write_atomic
from ..sim.physics import Scenario, demo_scenario
from ..wire.dialect import Dialect
from ..wire.protocol import (
    ACCEL_COUNTS_PER_G,
    MAX_LINE,
    RECORD_FIELDS,
    RECORD_VERSION,
    ParseError,
    calibration_from_record,
    encode_line,
    parse_command,
    record_crc,
)
from .faults import Fault, FaultKind, LinkFaults
from .protocol_client import ProtocolDevice
from .port import Port, chip_of, scenario_of

FIRMWARE = "0.1.0"
EEPROM_SIZE = 1024
EEPROM_MAGIC = 0x4D


def eeprom_of(port: Port, chip=None) -> str | None:
    """The EEPROM file a ``sim://`` port keeps, as ``emu://`` does: ``eeprom=PATH``; by default
    one per seed and chip in the user's state directory, so what ``calibrate`` wrote is there
    for ``show`` in the next command; None (a throwaway store) for ``eeprom=none``."""
    from ..recordings.state import board_eeprom, chip_suffix

    return board_eeprom(port.get("eeprom"), "sim", f"eeprom-seed{port.get('seed', 1)}{chip_suffix(chip)}.bin")


class SimEeprom:
    """1 KiB of EEPROM, optionally backed by a file (written through on every store)."""

    def __init__(self, path: str | None = None):
        self.path = path
        self.data = bytearray(b"\xff" * EEPROM_SIZE)
        if path and os.path.exists(path):
            with open(path, "rb") as f:
                raw = f.read(EEPROM_SIZE)
            self.data[: len(raw)] = raw

    def put(self, offset: int, payload: bytes) -> None:
        self.data[offset : offset + len(payload)] = payload
        if self.path:
            write_atomic(self.path, bytes(self.data))

    def load_record(self) -> tuple[str, tuple[int, ...]]:
        blob = bytes(self.data[: 1 + 4 * RECORD_FIELDS + 2])
        if all(b == 0xFF for b in blob):
            return "BLANK", (0,) * RECORD_FIELDS
        values = struct.unpack("<18i", blob[1 : 1 + 4 * RECORD_FIELDS])
        (crc,) = struct.unpack("<H", blob[-2:])
        if blob[0] != EEPROM_MAGIC or values[0] != RECORD_VERSION or record_crc(values) != crc:
            return "CORRUPT", (0,) * RECORD_FIELDS
        return "OK", values

    def save_record(self, values) -> None:
        blob = bytes([EEPROM_MAGIC]) + struct.pack("<18i", *values) + struct.pack("<H", record_crc(values))
        self.put(0, blob)


class StandaloneFit:
    """The firmware's own sphere fit (``F``; ``N``: its naive variant), as the AVR computes it:
    float32 sums of the samples centred on the first one (``N``: not centred), solved once
    ``n`` valid samples are in."""

    def __init__(self, tag: int, cmd: str, n: int, asa, ut_per_count: float = MPU9150.ut_per_count):
        self.tag, self.cmd, self.n, self.asa = tag, cmd, n, asa
        self.scale = ut_per_count / MPU9150.ut_per_count  # the chip's quantum over the AK8975's
        self.naive = cmd == "N"
        self._ref = None
        self._pts: list = []

    def add(self, raw, st2: int) -> bool:
        """One measurement (a flagged one is skipped); True once ``n`` are in."""
        if st2 & 0x0C:
            return False
        m = (counts_to_ut(raw, self.asa) * self.scale).astype(np.float32)
        if self._ref is None:
            self._ref = m.copy()
        self._pts.append(m - (self._ref if not self.naive else 0))
        return len(self._pts) >= self.n

    def solve(self):
        """(n, offset nT ×3, radius nT, condition × 10⁹) as the ``F`` reply carries them; None
        when the normal matrix is singular."""
        p = np.array(self._pts, np.float32)
        a = np.column_stack([2 * p, np.ones(len(p), np.float32)]).astype(np.float32)
        b = (p * p).sum(axis=1).astype(np.float32)
        ata = (a.T @ a).astype(np.float32)
        atb = (a.T @ b).astype(np.float32)
        try:
            x = np.linalg.solve(ata, atb)
        except np.linalg.LinAlgError:
            return None
        c = x[:3] + (0 if self.naive else self._ref)
        r = float(np.sqrt(max(0.0, x[3] + float(x[:3] @ x[:3]))))
        ev = np.linalg.eigvalsh(ata.astype(np.float64))
        cond = int(min(1e9, 1000 * ev[0] / max(ev[-1], 1e-30) * 1e6))
        return len(p), [int(round(v * 1000)) for v in c], int(round(r * 1000)), cond


class SerialEnd:
    """The device end of a serial line, for a simulated board: what the host writes is cut into
    command lines (``_command``); what the board emits waits in ``_out`` until the host reads it,
    each read within its ``timeout`` (``_advance`` lets the board produce what is due meanwhile).
    The link faults (``self.link``, ``LinkFaults``) act here: an unplugged end raises
    ``OSError``, a stalled one moves nothing."""

    def __init__(self, link: LinkFaults, clock=time.monotonic):
        self.link = link
        self.timeout: float | None = 0.05
        self._clock = clock
        self._lock = threading.Lock()
        self._out = bytearray()
        self._in = bytearray()
        self._closed = False

    def _advance(self, wait_s: float) -> None:
        """Produce what is due (a board's measurements)."""

    def _command(self, line: bytes) -> None:
        """Take one command line."""

    def _boot(self) -> None:
        """Power up (after a replug)."""

    def _emit(self, kind: str, *fields) -> None:
        """Send one line."""

    # -- transport surface -------------------------------------------------------------------
    @property
    def in_waiting(self) -> int:
        with self._lock:
            self._check_port()
            if self.link.stalled:
                return 0
            self._advance(0.0)
            return len(self._out)

    def write(self, data: bytes) -> int:
        if self._closed:
            raise OSError("sim board closed")
        with self._lock:
            self._check_port()
            if self.link.stalled:
                return len(data)
            self._in += data
            while b"\n" in self._in:
                line, _, rest = bytes(self._in).partition(b"\n")
                self._in = bytearray(rest)
                self._command(line)
            if len(self._in) > MAX_LINE:  # an over-long command: answer and drop it
                self._in.clear()
                self._emit("E", 0, "?", "LONG")
        return len(data)

    def read(self, n: int = 1) -> bytes:
        if self._closed:
            raise OSError("sim board closed")
        deadline = self._clock() + (self.timeout or 0.0)
        while True:
            with self._lock:
                self._check_port()
                if self.link.stalled:
                    if self._clock() >= deadline:
                        return b""
                    time.sleep(min(0.005, max(0.0, deadline - self._clock())))
                    continue
                self._advance(max(0.0, deadline - self._clock()))
                if self._out:
                    chunk = bytes(self._out[:n])
                    del self._out[:n]
                    return chunk
            if self._clock() >= deadline:
                return b""
            time.sleep(min(0.005, max(0.0, deadline - self._clock())))

    def reset_input_buffer(self) -> None:
        with self._lock:
            self._out.clear()

    def close(self) -> None:
        self._closed = True

    def _check_port(self) -> None:
        """Raise OSError while unplugged; a replugged board boots (a USB reconnect resets it)."""
        if self.link.settle(drained=not self._out):
            self._boot()
        self.link.check_present("sim board")

    @property
    def present(self) -> bool:
        with self._lock:
            try:
                self._check_port()
            except OSError:
                return False
            return True

    def plug_in(self) -> "SerialEnd":
        """The connector: the host opens the port. A closed board comes back (and boots, as a
        USB reconnect resets an Arduino); still unplugged ⇒ PortUnavailable."""
        with self._lock:
            try:
                self._check_port()
            except OSError as exc:
                raise PortUnavailable(f"cannot open the simulated board: {exc}") from None
            if self._closed:
                self._closed = False
                self._in.clear()
                self._out.clear()
                self._boot()
        return self


REAL_TIME = 1.0  # sim:// keeps time like a board unless told otherwise (pace=0)


class SimBoard(SerialEnd):
    """The simulated board as a pyserial-like transport (read/write/in_waiting/timeout/close)."""

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        rate_hz: int = 100,
        pace: float = 0.0,
        eeprom_path: str | None = None,
        asa: tuple[int, int, int] | None = None,
        faults: tuple[Fault, ...] = (),
        clock=time.monotonic,
        accel: bool = True,
    ):
        self.scenario = scenario or demo_scenario()
        self.chip = self.scenario.physics.chip  # the part on the board: its ids, quantum, range
        self.asa = tuple(asa or self.scenario.physics.asa) if self.chip.has_asa else NEUTRAL_ASA
        self.rate_hz = rate_hz
        self.pace = pace
        self.eeprom = SimEeprom(eeprom_path)
        self.accel = accel  # samples carry the accelerometer's three registers (a board without one: False)
        super().__init__(LinkFaults(faults, clock), clock)  # the scheduled faults and the link they act on
        self.faults: dict = {}  # board flags in effect: mute, no_write_ack, corrupt_write
        self.sent: Counter = Counter()  # lines emitted, by kind (tests count samples sent)
        self._boot()
        self._fire_due()  # faults without a time are in effect from power-up

    @classmethod
    def from_port(cls, port: Port, scenario: Scenario | None = None) -> "SimBoard":
        """The board a ``sim://`` port string describes (``scenario`` overrides its physics)."""
        scenario = scenario or scenario_of(port)
        chip = chip_of(port)
        return cls(scenario if chip is None else scenario.on_chip(chip), rate_hz=port.get("rate", 100),
                   pace=port.get("pace", REAL_TIME), eeprom_path=eeprom_of(port, chip), faults=port.faults,
                   accel=port.get("accel", True))

    # -- board state -------------------------------------------------------------------------
    def _boot(self) -> None:
        self._seq = 0
        self._ms = 0.0  # device millis() as float ms
        self._k = getattr(self, "_k", 0)  # measurement index keeps counting: physics time goes on
        self._t0_s = getattr(self, "_t_s", 0.0)
        self._t_s = self._t0_s
        self._streaming = False
        self._mode = 0
        self._wall0 = self._clock()
        self._sim0_ms = 0.0
        self._fit = None
        self._hello()

    def _hello(self) -> None:
        """The hello the sketch sends: protocol 1, the chip's ids, ASA, rate and resolution."""
        chip = self.chip
        self._emit("H", 1, FIRMWARE, f"{chip.who_am_i[0]:02X}", f"{chip.mag_id:02X}", *self.asa, self.rate_hz, chip.bits)

    def _emit(self, kind: str, *fields) -> None:
        self.sent[kind] += 1
        self._out += encode_line(kind, (self._seq, *fields))
        self._seq = (self._seq + 1) % 65536

    # -- simulation --------------------------------------------------------------------------
    def _advance(self, wait_s: float) -> None:
        """Produce the samples that are due. Unpaced, produce a batch whenever the host reads."""
        if (not self._streaming and self._fit is None) or self.link.waiting:
            return
        period_ms = 1000.0 / self.rate_hz
        if self.pace > 0:
            target_ms = self._sim0_ms + (self._clock() - self._wall0) * 1000.0 * self.pace
            due = int((target_ms - self._ms) // period_ms)
        else:
            due = 0 if len(self._out) > 4096 else 64
        if due <= 0:
            return
        due = min(due, 2000)
        if self.link.pending:  # stop the batch at the next scheduled fault so it fires in place
            due = max(1, min(due, int(np.ceil((self.link.next_s() - self._t_s) * 1000.0 / period_ms))))
        ms = self._ms + period_ms * np.arange(1, due + 1)
        k = self._k + np.arange(due)
        t_s = self._t0_s + ms / 1000.0
        raw, st2, temp = self.scenario.measure(t_s, k)
        accel = accel_counts(self.scenario.accel_body_g(t_s, k), self.chip)
        self._k += due
        self._ms = float(ms[-1])
        self._t_s = float(t_s[-1])
        for i in range(due):
            self._measurement(int(ms[i]), raw[i], int(st2[i]), int(temp[i]), accel[i])
        self._fire_due()

    def _measurement(self, ms: int, raw, st2: int, temp: int, accel) -> None:
        hx, hy, hz = (int(v) for v in raw)
        more = tuple(int(v) for v in accel) if self.accel else ()
        if self._fit is not None:
            self._fit_add(hx, hy, hz, st2)
        if not self._streaming:
            return
        if self._mode == 1:
            status, values = self.eeprom.load_record()
            h = self._apply(values, (hx, hy, hz), temp)
            self._emit("U", ms, *h, st2, temp, *more)
        else:
            self._emit("S", ms, hx, hy, hz, st2, temp, *more)

    def _apply(self, values, raw, temp_raw) -> tuple[int, int, int]:
        """The stored record applied to one reading, in nT (what a ``U`` line carries)."""
        cal = calibration_from_record(values)
        m_ut = counts_to_ut(raw, self.asa) * (self.chip.ut_per_count / MPU9150.ut_per_count)
        h_ut = cal.correct(m_ut, {"temp_c": [temp_raw_to_c(temp_raw, self.chip)]})[0]
        return tuple(int(round(x * 1000.0)) for x in h_ut)

    # -- the firmware's standalone fit ------------------------------------------------------
    def _fit_add(self, hx, hy, hz, st2) -> None:
        if not self._fit.add((hx, hy, hz), st2):
            return
        f, self._fit = self._fit, None
        solved = f.solve()
        if solved is None:
            self._emit("E", f.tag, f.cmd, "RANGE")
            return
        n, o_nt, r_nt, cond = solved
        self._emit("F", f.tag, n, *o_nt, r_nt, cond)
        if not f.naive:
            values = (RECORD_VERSION, *o_nt, r_nt, 10**6, 10**6, 10**6, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            self.eeprom.save_record(values)
            self._emit_record(f.tag)

    # -- commands ------------------------------------------------------------------------------
    def _emit_record(self, tag: int) -> None:
        status, values = self.eeprom.load_record()
        self._emit("C", tag, status, *values, f"{record_crc(values) if status == 'OK' else 0:04X}")

    def _command(self, line: bytes) -> None:
        if self.faults.get("mute"):
            return
        start = line.rfind(b"$")
        if start < 0:
            if line.strip():
                self._emit("E", 0, "?", "SYNTAX")
            return
        try:
            cmd, tag, args = parse_command(line[start:])
        except ParseError as exc:
            self._emit("E", 0, "?", str(exc))
            return
        try:
            self._dispatch(cmd, tag, [int(a) if a.lstrip(b"-").isdigit() else a.decode() for a in args])
        except (ValueError, IndexError):
            self._emit("E", tag, cmd, "SYNTAX")

    def _dispatch(self, cmd: str, tag: int, args: list) -> None:
        if cmd == "I":
            self._emit("A", tag, "I")
            self._hello()
        elif cmd == "G":
            self._emit("A", tag, "G")
            self._streaming = True
            self._wall0, self._sim0_ms = self._clock(), self._ms
        elif cmd == "X":
            self._emit("A", tag, "X")
            self._streaming = False
        elif cmd == "R":
            hz = int(args[0])
            if not 1 <= hz <= 100:
                self._emit("E", tag, "R", "RANGE")
                return
            self.rate_hz = hz
            self._wall0, self._sim0_ms = self._clock(), self._ms
            self._emit("A", tag, "R", hz)
        elif cmd == "M":
            mode = int(args[0])
            if mode not in (0, 1) or (mode == 1 and self.eeprom.load_record()[0] != "OK"):
                self._emit("E", tag, "M", "RANGE")
                return
            self._mode = mode
            self._emit("A", tag, "M", mode)
        elif cmd == "K":
            self._emit_record(tag)
        elif cmd == "D":  # discard the stored record: the store is blank again, nothing applied
            self.eeprom.put(0, b"\xff" * (1 + 4 * RECORD_FIELDS + 2))
            self._mode = 0
            self._emit("A", tag, "D")
            self._emit_record(tag)
        elif cmd == "W":
            if len(args) != RECORD_FIELDS + 1:
                self._emit("E", tag, "W", "SYNTAX")
                return
            values = tuple(int(a) for a in args[:RECORD_FIELDS])
            crc = int(str(args[-1]), 16)
            if values[0] != RECORD_VERSION:
                self._emit("E", tag, "W", "RANGE")
                return
            if record_crc(values) != crc:
                self._emit("E", tag, "W", "RECCRC")
                return
            if self.faults.get("no_write_ack"):
                return
            if self.faults.get("corrupt_write"):  # True: the next write only; "always": every write
                if self.faults["corrupt_write"] != "always":
                    self.faults["corrupt_write"] = False
                values = (values[0], values[1] + 1000, *values[2:])
            self.eeprom.save_record(values)
            self._emit("A", tag, "W")
            self._emit_record(tag)
        elif cmd == "Z":
            self._emit("A", tag, "Z")
            self._boot()
        elif cmd == "T":  # the AK8975 self-test: the coil's reading from the physics, this chip's ASA
            self._emit("A", tag, "T", *replace(self.scenario.physics, asa=self.asa).self_test_raw(), 0)
        elif cmd in ("F", "N"):
            n = int(args[0])
            if not 50 <= n <= 2000:
                self._emit("E", tag, cmd, "RANGE")
                return
            if self._fit is not None:
                self._emit("E", tag, cmd, "BUSY")
                return
            self._fit = StandaloneFit(tag, cmd, n, self.asa, self.chip.ut_per_count)
            self._wall0, self._sim0_ms = self._clock(), self._ms
            self._emit("A", tag, cmd, n)
        else:
            self._emit("E", tag, "?", "UNKNOWN")  # as the firmware and docs/protocol.md (Versioning)

    def power_cycle(self) -> None:
        """An unsolicited reset (brown-out, watchdog): a fresh hello with seq 0, EEPROM kept."""
        with self._lock:
            self._boot()

    # -- fault injection -------------------------------------------------------------------------
    def inject(self, fault: Fault) -> None:
        """Make a fault happen now (see ``magcal.devices.faults`` for the kinds)."""
        kind = fault.kind
        if kind in (FaultKind.UNPLUG, FaultKind.STALL):
            self.link.interrupt(fault)
        elif kind is FaultKind.RESET:
            self._out += self.link.torn(encode_line("S", (self._seq, int(self._ms), 1, 2, 3, 0, 0)))
            self._boot()
        elif kind is FaultKind.GARBAGE:
            self._out += self.link.noise(fault.value)
        elif kind is FaultKind.HARD_IRON:
            self.scenario = self.scenario.with_physics(hard_iron_ut=tuple(float(v) for v in fault.value))
        else:  # mute, no_write_ack, corrupt_write
            self.faults[kind.value] = True

    def _fire_due(self) -> None:
        for fault in self.link.due(self._t_s):
            self.inject(fault)


def accel_counts(accel_g: np.ndarray, chip) -> np.ndarray:
    """The physics' accelerometer readings in g (its body frame, which is the magnetometer's) →
    the IMU's ACCEL_*OUT signed counts at ±2 g, in the IMU's own axes (``chip.mag_from_accel``
    undone), as a real board sends them."""
    counts = np.round(chip.mag_to_accel(accel_g) * ACCEL_COUNTS_PER_G)
    return np.clip(counts, -32768, 32767).astype(np.int64)


def serve_fd(board: SimBoard, fd: int) -> None:
    """Run ``board`` behind a file descriptor (a pty master) until the other side closes it,
    so a host can open the pty's slave as a serial port exactly as it opens /dev/ttyACM0."""
    os.set_blocking(fd, False)
    while True:
        try:
            cmd = os.read(fd, 4096)
            if cmd:
                board.write(cmd)
        except BlockingIOError:
            pass
        except OSError:
            return  # the host side is gone
        out = board.read(4096)
        if out:
            try:
                os.write(fd, out)
            except OSError:
                return


def open_sim(port: Port, dialect: Dialect = Dialect.NATIVE, *, board: SimBoard | None = None,
             scenario: Scenario | None = None, tap=None, reply_timeout_s: float = 1.5,
             boot_timeout_s: float = 3.0) -> ProtocolDevice:
    """The v1 client on a simulated board: ``board`` when given, else the one ``port`` describes."""
    board = board or SimBoard.from_port(port, scenario)
    dev = ProtocolDevice(port.url, board.plug_in, transport_name="sim", tap=tap,
                         reply_timeout_s=reply_timeout_s, boot_timeout_s=boot_timeout_s)
    dev.board = board
    return dev
