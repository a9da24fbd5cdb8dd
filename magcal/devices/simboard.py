"""``sim://`` — a pure-Python simulated board that speaks protocol v1 as bytes.

It is a *transport*: the host's real protocol client (``ProtocolDevice``) talks to it exactly as
it talks to a serial port, so every layer above runs unchanged. Its sensor readings come from
the one physics simulator (``magcal.sim.physics``); its EEPROM persists to a file when given one.

URL options (query string): ``seed=N`` (physics seed), ``rate=HZ`` (initial rate, default 100),
``speed=X`` (0 = as fast as the host reads, 1 = real time, N = N× real time; default 0),
``eeprom=PATH`` (persist EEPROM), ``motion=sphere|tilt|yaw|still``,
``offset=x,y,z`` (hard iron µT), ``noise=UT``, ``field=UT``.
Fault injection, for tests of the layers above, goes through ``SimBoard.faults`` (flags:
``mute``, ``no_write_ack``, ``corrupt_write``, ``unplugged``, ``stall``) or the URL option
``fault=KIND[@T][+D][=VALUE]``, repeatable, fired when the board's physics time reaches T s:

- ``unplug@T+D``: the port vanishes for D wall seconds (default 0.5): reads, writes and opens
  fail with OSError/PortUnavailable; on replug the board boots afresh (a USB reconnect resets it);
- ``stall@T+D``: no bytes out and no command handled for D wall seconds (default 1);
- ``reset@T``: a line torn in the middle, then a fresh boot hello (seq 0), not streaming;
- ``garbage@T=N``: a burst of N random bytes (default 200) in the middle of the stream;
- ``hard_iron@T=x,y,z``: the physics' hard iron becomes (x, y, z) µT (a payload was added);
- ``mute@T``, ``no_write_ack@T``, ``corrupt_write@T``: set that flag from T on (T = 0 if omitted;
  ``corrupt_write`` spoils the next write only).

A URL with ``fault=`` or ``board=NAME`` names one simulated device: opening the same URL (or
name) again reconnects to the same board — the same EEPROM, physics time and pending faults —
as replugging a real board would (``forget_boards()`` drops them).
"""

from __future__ import annotations

import os
import struct
import threading
import time
from collections import Counter
from dataclasses import replace
from urllib.parse import parse_qs, urlsplit

import numpy as np

from ..core.errors import DeviceError
from ..core.sample import counts_to_ut, temp_raw_to_c
from ..recordings.atomic import write_atomic
from ..sim.physics import Motion, Scenario, demo_scenario
from ..wire.protocol import (
    MAX_LINE,
    RECORD_FIELDS,
    RECORD_VERSION,
    ParseError,
    calibration_from_record,
    encode_line,
    parse_command,
    record_crc,
)
from .link import ProtocolDevice

FIRMWARE = "0.1.0"
EEPROM_SIZE = 1024
EEPROM_MAGIC = 0x4D


class SimEeprom:
    """1 KiB of EEPROM, optionally backed by a file (written through on every store)."""

    def __init__(self, path: str | None = None):
        self.path = path
        self.data = bytearray(b"\xff" * EEPROM_SIZE)
        if path and os.path.exists(path):
            with open(path, "rb") as f:
                raw = f.read(EEPROM_SIZE)
            self.data[: len(raw)] = raw

    def store(self, offset: int, payload: bytes) -> None:
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
        self.store(0, blob)


class SimBoard:
    """The simulated board as a pyserial-like transport (read/write/in_waiting/timeout/close)."""

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        rate_hz: int = 100,
        speed: float = 0.0,
        eeprom_path: str | None = None,
        asa: tuple[int, int, int] | None = None,
        clock=time.monotonic,
    ):
        self.scenario = scenario or demo_scenario()
        self.asa = tuple(asa or self.scenario.physics.asa)
        self.rate_hz = rate_hz
        self.speed = speed
        self.eeprom = SimEeprom(eeprom_path)
        self.timeout: float | None = 0.05
        self.faults: dict = {}
        self.schedule: list[tuple[float, str, float, object]] = []  # (t_s, kind, duration_s, value)
        self.fired: list[tuple[float, str]] = []
        self.sent: Counter = Counter()  # lines emitted, by kind (tests count samples sent)  # faults that went off, at what physics time
        self._until: dict[str, float] = {}  # wall-clock end of unplug/stall
        self._after_drain: dict[str, float] = {}  # unplug/stall wait until the host read what came before
        self._rng = np.random.default_rng(0xFA17)
        self._clock = clock
        self._lock = threading.Lock()
        self._out = bytearray()
        self._in = bytearray()
        self._closed = False
        self._boot()

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
        self._emit("H", 1, FIRMWARE, "68", "48", *self.asa, self.rate_hz)

    def _emit(self, kind: str, *fields) -> None:
        self.sent[kind] += 1
        self._out += encode_line(kind, (self._seq, *fields))
        self._seq = (self._seq + 1) % 65536

    # -- transport surface -------------------------------------------------------------------
    @property
    def in_waiting(self) -> int:
        with self._lock:
            self._check_port()
            if self.faults.get("stall"):
                return 0
            self._advance(0.0)
            return len(self._out)

    def write(self, data: bytes) -> int:
        if self._closed:
            raise OSError("sim board closed")
        with self._lock:
            self._check_port()
            if self.faults.get("stall"):
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
                if self.faults.get("stall"):
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

    # -- simulation --------------------------------------------------------------------------
    def _advance(self, wait_s: float) -> None:
        """Produce the samples that are due. Unpaced, produce a batch whenever the host reads."""
        if (not self._streaming and self._fit is None) or self._after_drain:
            return
        period_ms = 1000.0 / self.rate_hz
        if self.speed > 0:
            target_ms = self._sim0_ms + (self._clock() - self._wall0) * 1000.0 * self.speed
            due = int((target_ms - self._ms) // period_ms)
        else:
            due = 0 if len(self._out) > 4096 else 64
        if due <= 0:
            return
        due = min(due, 2000)
        if self.schedule:  # stop the batch at the next scheduled fault so it fires in place
            t_next = min(t for t, *_ in self.schedule)
            due = max(1, min(due, int(np.ceil((t_next - self._t_s) * 1000.0 / period_ms))))
        ms = self._ms + period_ms * np.arange(1, due + 1)
        k = self._k + np.arange(due)
        t_s = self._t0_s + ms / 1000.0
        raw, st2, temp = self.scenario.measure(t_s, k)
        self._k += due
        self._ms = float(ms[-1])
        self._t_s = float(t_s[-1])
        for i in range(due):
            self._measurement(int(ms[i]), raw[i], int(st2[i]), int(temp[i]))
        self._fire_due()

    def _measurement(self, ms: int, raw, st2: int, temp: int) -> None:
        hx, hy, hz = (int(v) for v in raw)
        if self._fit is not None:
            self._fit_add(hx, hy, hz, st2)
        if not self._streaming:
            return
        if self._mode == 1:
            status, values = self.eeprom.load_record()
            h = self._apply(values, (hx, hy, hz), temp)
            self._emit("U", ms, *h, st2, temp)
        else:
            self._emit("S", ms, hx, hy, hz, st2, temp)

    def _apply(self, values, raw, temp_raw) -> tuple[int, int, int]:
        """The stored record applied to one reading, in nT (what a ``U`` line carries)."""
        cal = calibration_from_record(values)
        h_ut = cal.correct(counts_to_ut(raw, self.asa), {"temp_c": [temp_raw_to_c(temp_raw)]})[0]
        return tuple(int(round(x * 1000.0)) for x in h_ut)

    # -- standalone fit (centred float32 sums, as the firmware does) --------------------------
    def _fit_add(self, hx, hy, hz, st2) -> None:
        f = self._fit
        if st2 & 0x0C:
            return
        m = counts_to_ut((hx, hy, hz), self.asa).astype(np.float32)
        if f["ref"] is None:
            f["ref"] = m.copy()
        f["pts"].append(m - (f["ref"] if not f["naive"] else 0))
        if len(f["pts"]) >= f["n"]:
            self._fit_finish()

    def _fit_finish(self) -> None:
        f = self._fit
        self._fit = None
        p = np.array(f["pts"], np.float32)
        a = np.column_stack([2 * p, np.ones(len(p), np.float32)]).astype(np.float32)
        b = (p * p).sum(axis=1).astype(np.float32)
        ata = (a.T @ a).astype(np.float32)
        atb = (a.T @ b).astype(np.float32)
        try:
            x = np.linalg.solve(ata.astype(np.float32), atb.astype(np.float32))
        except np.linalg.LinAlgError:
            self._emit("E", f["tag"], f["cmd"], "RANGE")
            return
        c = x[:3] + (0 if f["naive"] else f["ref"])
        r = float(np.sqrt(max(0.0, x[3] + float(x[:3] @ x[:3]))))
        ev = np.linalg.eigvalsh(ata.astype(np.float64))
        cond = int(min(1e9, 1000 * ev[0] / max(ev[-1], 1e-30) * 1e6))
        o_nt = [int(round(v * 1000)) for v in c]
        self._emit("F", f["tag"], len(p), *o_nt, int(round(r * 1000)), cond)
        if not f["naive"]:
            values = (RECORD_VERSION, *o_nt, int(round(r * 1000)), 10**6, 10**6, 10**6, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            self.eeprom.save_record(values)
            self._emit_record(f["tag"])

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
            self._emit("H", 1, FIRMWARE, "68", "48", *self.asa, self.rate_hz)
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
            self._fit = {"tag": tag, "cmd": cmd, "n": n, "naive": cmd == "N", "ref": None, "pts": []}
            self._wall0, self._sim0_ms = self._clock(), self._ms
            self._emit("A", tag, cmd, n)
        else:
            self._emit("E", tag, "?", "UNKNOWN")  # as the firmware and PROTOCOL.md (Versioning)

    def power_cycle(self) -> None:
        """An unsolicited reset (brown-out, watchdog): a fresh hello with seq 0, EEPROM kept."""
        with self._lock:
            self._boot()

    # -- fault injection -------------------------------------------------------------------------
    def _check_port(self) -> None:
        """Raise OSError while unplugged; end unplug/stall whose wall-clock time is over."""
        now = self._clock()
        if self._after_drain and not self._out:
            for kind, duration in self._after_drain.items():
                flag = "unplugged" if kind == "unplug" else kind
                self.faults[flag] = True
                self._until[flag] = now + duration
            self._after_drain.clear()
        if self.faults.get("stall") and now >= self._until.get("stall", float("inf")):
            self.faults["stall"] = False
        if self.faults.get("unplugged"):
            if now < self._until.get("unplugged", float("inf")):
                raise OSError("sim board unplugged (device not present)")
            self.faults["unplugged"] = False
            self._boot()  # replugged: USB power-up resets the board

    @property
    def present(self) -> bool:
        with self._lock:
            try:
                self._check_port()
            except OSError:
                return False
            return True

    def inject(self, kind: str, duration_s: float | None = None, value=None) -> None:
        """Make a fault happen now (see the module docstring for the kinds)."""
        if kind in ("unplug", "stall"):
            # takes effect once the host has read what was sent before T (deterministic tests)
            self._after_drain[kind] = (0.5 if kind == "unplug" else 1.0) if duration_s is None else duration_s
        elif kind == "reset":
            line = encode_line("S", (self._seq, int(self._ms), 1, 2, 3, 0, 0))
            self._out += line[: len(line) // 2]  # the reset cuts the line being sent
            self._boot()
        elif kind == "garbage":
            n = 200 if value is None else int(value)
            self._out += self._rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        elif kind == "hard_iron":
            self.scenario = self.scenario.with_physics(hard_iron_ut=tuple(float(v) for v in value))
        elif kind in ("mute", "no_write_ack", "corrupt_write"):
            self.faults[kind] = True
        else:
            raise DeviceError(f"unknown sim fault {kind!r}; known: {', '.join(FAULT_KINDS)}")
        self.fired.append((self._t_s, kind))

    def _fire_due(self) -> None:
        due = [f for f in self.schedule if f[0] <= self._t_s + 1e-9]
        if not due:
            return
        self.schedule = [f for f in self.schedule if f[0] > self._t_s + 1e-9]
        for _, kind, duration, value in sorted(due, key=lambda f: f[0]):
            self.inject(kind, duration, value)

    def replug(self) -> None:
        """The host opens the port again: a closed board comes back (and boots, as a USB
        reconnect resets an Arduino); still unplugged ⇒ OSError."""
        with self._lock:
            self._check_port()
            if self._closed:
                self._closed = False
                self._in.clear()
                self._out.clear()
                self._boot()


FAULT_KINDS = ("unplug", "stall", "reset", "garbage", "hard_iron", "mute", "no_write_ack", "corrupt_write")


def parse_fault(spec: str) -> tuple[float, str, float | None, object]:
    """``KIND[@T][+D][=VALUE]`` → (t_s, kind, duration_s, value); DeviceError when malformed."""
    head, _, value = spec.partition("=")
    head, _, dur = head.replace(" ", "+").partition("+")  # a '+' in a URL query arrives as ' '
    kind, _, at = head.partition("@")
    kind = kind.strip()
    if kind not in FAULT_KINDS:
        raise DeviceError(f"unknown sim fault {kind!r} in {spec!r}; known: {', '.join(FAULT_KINDS)}")
    try:
        t_s = float(at.rstrip("s")) if at else 0.0
        duration = float(dur.rstrip("s")) if dur else None
        if kind == "hard_iron":
            v = tuple(float(x) for x in value.split(","))
            if len(v) != 3:
                raise ValueError("hard_iron takes x,y,z in µT")
            val: object = v
        elif kind == "garbage":
            val = int(value) if value else None
        else:
            val = None
    except ValueError as exc:
        raise DeviceError(f"bad sim fault {spec!r}: {exc}") from None
    if t_s < 0 or (duration is not None and duration < 0):
        raise DeviceError(f"bad sim fault {spec!r}: times must be ≥ 0")
    return t_s, kind, duration, val


_BOARDS: dict[str, SimBoard] = {}


def forget_boards() -> None:
    """Drop the named boards kept for reconnection (tests call this between cases)."""
    _BOARDS.clear()


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


def parse_sim_url(url: str) -> dict:
    """``sim://?seed=3&rate=50`` → options dict (values validated, with clear errors)."""
    parts = urlsplit(url)
    multi = parse_qs(parts.query, keep_blank_values=True)
    q = {k: v[-1] for k, v in multi.items()}
    known = {"seed", "rate", "speed", "eeprom", "motion", "offset", "noise", "field", "fault", "board"}
    unknown = set(q) - known
    if unknown:
        raise DeviceError(f"sim:// does not know option(s) {sorted(unknown)}; known: {sorted(known)}")
    try:
        opts = {
            "seed": int(q.get("seed", 1)),
            "rate": int(q.get("rate", 100)),
            "speed": float(q.get("speed", 0)),
            "eeprom": q.get("eeprom") or None,
            "motion": q.get("motion", "sphere"),
            "offset": tuple(float(x) for x in q["offset"].split(",")) if "offset" in q else None,
            "noise": float(q["noise"]) if "noise" in q else None,
            "field": float(q["field"]) if "field" in q else None,
            "faults": [parse_fault(f) for v in multi.get("fault", []) for f in v.split(";") if f],
            "board": q.get("board") or None,
        }
    except ValueError as exc:
        raise DeviceError(f"bad sim:// option in {url!r}: {exc}") from exc
    if opts["offset"] is not None and len(opts["offset"]) != 3:
        raise DeviceError("sim:// offset takes three comma-separated numbers (µT)")
    if not 1 <= opts["rate"] <= 100:
        raise DeviceError("sim:// rate must be 1…100 Hz")
    return opts


def scenario_from_options(opts: dict) -> Scenario:
    sc = demo_scenario(opts["seed"])
    if opts["motion"] != "sphere":
        try:
            sc = replace(sc, motion=Motion(opts["motion"]))
        except ValueError as exc:
            raise DeviceError(str(exc)) from exc
    changes = {}
    if opts["offset"] is not None:
        changes["hard_iron_ut"] = opts["offset"]
    if opts["noise"] is not None:
        changes["noise_ut"] = opts["noise"]
    if opts["field"] is not None:
        changes["field_ut"] = opts["field"]
    return sc.with_physics(**changes) if changes else sc


def open_sim(url: str, dialect: str = "native", scenario: Scenario | None = None, **options) -> ProtocolDevice:
    opts = parse_sim_url(url)
    key = opts["board"] or (url if opts["faults"] else None)
    board = _BOARDS.get(key) if key else None
    if board is not None:
        try:
            board.replug()
        except OSError as exc:
            from ..core.errors import PortUnavailable

            raise PortUnavailable(f"cannot open {url}: {exc}") from None
    else:
        board = SimBoard(
            scenario or scenario_from_options(opts),
            rate_hz=opts["rate"],
            speed=opts["speed"],
            eeprom_path=opts["eeprom"],
        )
        board.schedule = list(opts["faults"])
        board._fire_due()  # faults without a time are in effect from power-up
        if key:
            _BOARDS[key] = board
    dev = ProtocolDevice(url, board, transport_name="sim", **options)
    dev.board = board  # tests reach the simulated hardware through this
    return dev
