"""``sim://`` — a pure-Python simulated board that speaks protocol v1 as bytes.

It is a *transport*: the host's real protocol client (``ProtocolDevice``) talks to it exactly as
it talks to a serial port, so every layer above runs unchanged. Its sensor readings come from
the one physics simulator (``magcal.physics``); its EEPROM persists to a file when given one.

URL options (query string): ``seed=N`` (physics seed), ``rate=HZ`` (initial rate, default 100),
``speed=X`` (0 = as fast as the host reads, 1 = real time, N = N× real time; default 0),
``eeprom=PATH`` (persist EEPROM), ``motion=sphere|tilt|yaw|still``,
``offset=x,y,z`` (hard iron µT), ``noise=UT``, ``field=UT``.
Fault injection, for tests of the layers above, goes through ``SimBoard.faults``.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from dataclasses import replace
from urllib.parse import parse_qs, urlsplit

import numpy as np

from ..errors import DeviceError
from ..physics import Motion, Scenario, demo_scenario
from ..protocol import (
    MAX_LINE,
    RECORD_FIELDS,
    RECORD_VERSION,
    ParseError,
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
            tmp = self.path + ".tmp"
            with open(tmp, "wb") as f:
                f.write(self.data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)

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
        self._out += encode_line(kind, (self._seq, *fields))
        self._seq = (self._seq + 1) % 65536

    # -- transport surface -------------------------------------------------------------------
    @property
    def in_waiting(self) -> int:
        with self._lock:
            self._advance(0.0)
            return len(self._out)

    def write(self, data: bytes) -> int:
        if self._closed:
            raise OSError("sim board closed")
        with self._lock:
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
        if not self._streaming and self._fit is None:
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
        ms = self._ms + period_ms * np.arange(1, due + 1)
        k = self._k + np.arange(due)
        t_s = self._t0_s + ms / 1000.0
        raw, st2, temp = self.scenario.measure(t_s, k)
        self._k += due
        self._ms = float(ms[-1])
        self._t_s = float(t_s[-1])
        for i in range(due):
            self._measurement(int(ms[i]), raw[i], int(st2[i]), int(temp[i]))

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
        gain = np.array([(a + 128) / 256.0 for a in self.asa]) * 0.3
        m_nt = np.asarray(raw, float) * gain * 1000.0
        o = np.asarray(values[1:4], float)
        t = np.asarray(values[11:14], float)
        temp_c = temp_raw / 340.0 + 36.53
        d = m_nt - o - t * (temp_c - values[14] / 100.0)
        w00, w11, w22, w01, w02, w12 = (v / 1e6 for v in values[5:11])
        w = np.array([[w00, w01, w02], [w01, w11, w12], [w02, w12, w22]])
        h = w @ d
        return tuple(int(round(x)) for x in h)

    # -- standalone fit (centred float32 sums, as the firmware does) --------------------------
    def _fit_add(self, hx, hy, hz, st2) -> None:
        f = self._fit
        if st2 & 0x0C:
            return
        gain = np.array([(a + 128) / 256.0 for a in self.asa], np.float32) * np.float32(0.3)
        m = np.array([hx, hy, hz], np.float32) * gain
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
            self._emit("E", tag, cmd, "UNKNOWN")

    def power_cycle(self) -> None:
        """An unsolicited reset (brown-out, watchdog): a fresh hello with seq 0, EEPROM kept."""
        with self._lock:
            self._boot()


def parse_sim_url(url: str) -> dict:
    """``sim://?seed=3&rate=50`` → options dict (values validated, with clear errors)."""
    parts = urlsplit(url)
    q = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
    known = {"seed", "rate", "speed", "eeprom", "motion", "offset", "noise", "field"}
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
    board = SimBoard(
        scenario or scenario_from_options(opts),
        rate_hz=opts["rate"],
        speed=opts["speed"],
        eeprom_path=opts["eeprom"],
    )
    dev = ProtocolDevice(url, board, transport_name="sim", **options)
    dev.board = board  # tests reach the simulated hardware through this
    return dev
