"""Test support: a simulated Adafruit/PJRC calibration sketch on a pseudo-terminal.

``AdafruitBoard(...).start()`` opens a pty and runs a thread that behaves like the Adafruit_AHRS
``calibration`` example: per loop a ``Raw:`` line (mag = µT × 10, here rounded) and optionally a
``Uni:`` line, a ``Cal1:`` line at loop 50 and a ``Cal2:`` line at loop 100 of every 100, and a
receiver for the 68-byte packet (signature 117, 84; CRC-16 over all 68 bytes must be 0) that
stores the floats and prints ``Wrote calibration``. The field comes from
``magcal.sim.physics.Scenario`` — the one simulator — so tests know the truth.

Faults: ``noise`` (probability per line of garbage bytes ahead of it, or a garbage line),
``torn`` (probability that a line loses its tail and its ending), ``ending`` (``"\\r"``,
``"\\n"``, ``"\\r\\n"``), ``echo`` (``"ok"``; ``"never"`` — no packet handler and no Cal lines,
like a plain Raw: sketch; ``store_delay_loops`` delays storing, so Cal lines printed
before the store are still on the way when the host starts listening; ``"wrong"`` — stores the packet but echoes a hard-iron x 0.5 µT off;
``"ignore"`` — prints Cal lines with its defaults but has no packet handler).

The host opens ``board.port`` (the pty's slave path) like any serial port.
"""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty

import numpy as np

from magcal.sim.physics import Motion, Physics, Scenario
from magcal.wire import motioncal as mc

GRAVITY_MS2 = 9.8  # what the Adafruit sketch divides by for Raw: accel counts


def adafruit_scenario(seed: int = 3) -> Scenario:
    """A board with a large hard iron and visible soft iron, waved over the whole sphere."""
    return Scenario(
        physics=Physics(
            field_ut=48.0,
            hard_iron_ut=(31.7, -18.4, 42.9),
            distortion=((1.06, 0.03, -0.02), (0.03, 0.95, 0.015), (-0.02, 0.015, 1.01)),
            noise_ut=0.3,
        ),
        motion=Motion("sphere", period_s=8.0),
        seed=seed,
    )


class AdafruitBoard:
    def __init__(
        self,
        scenario: Scenario | None = None,
        rate_hz: float = 50.0,
        lines_per_s: float = 2000.0,
        ending: str = "\r\n",
        uni: bool = True,
        noise: float = 0.0,
        torn: float = 0.0,
        echo: str = "ok",
        cal_period: int = 100,
        seed: int = 0,
        banner: bool = True,
        store_delay_loops: int = 0,
    ):
        if echo not in ("ok", "never", "wrong", "ignore"):
            raise ValueError(f"echo mode {echo!r}")
        self.scenario = scenario or adafruit_scenario()
        self.rate_hz = rate_hz
        self.lines_per_s = lines_per_s
        self.ending = ending.encode()
        self.uni = uni
        self.noise = noise
        self.torn = torn
        self.echo = echo
        self.cal_period = cal_period
        self.banner = banner
        self.store_delay_loops = store_delay_loops
        self._loop = 0
        self._due: list[tuple[int, tuple]] = []  # (loop at which to store, packet floats)
        self.rng = np.random.default_rng(seed)
        # what the sketch holds (Adafruit_Sensor_Calibration defaults: identity, field 50)
        self.accel_zerog = [0.0, 0.0, 0.0]
        self.gyro_zerorate = [0.0, 0.0, 0.0]
        self.mag_hardiron = [0.0, 0.0, 0.0]
        self.mag_field = 50.0
        self.mag_softiron = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        self.packets_stored = 0
        self.crc_failures = 0
        self.readings = 0  # how many readings (Raw lines) were generated
        self.sent_field_ut: list[tuple] = []  # the µT value behind every reading, in order
        self._rx = bytearray()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.master = self.slave = -1
        self.port = ""

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "AdafruitBoard":
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: a raw byte pipe like USB CDC
        tty.setraw(self.master)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self._thread = threading.Thread(target=self._run, name="adafruit-board", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- the sketch ----------------------------------------------------------------------------
    def _emit(self, text: str) -> None:
        data = text.encode("latin-1")
        if self.noise and self.rng.random() < self.noise:
            junk = bytes(self.rng.integers(0, 256, int(self.rng.integers(1, 12))).tolist())
            # either garbage glued ahead of the line, or a garbage line of its own
            data = (junk.replace(b"\r", b"").replace(b"\n", b"") + data) if self.rng.random() < 0.5 \
                else junk + self.ending + data
        if self.torn and self.rng.random() < self.torn and len(data) > 4:
            self._write(data[: int(self.rng.integers(1, len(data) - 1))])  # tail and ending lost
            return
        self._write(data + self.ending)

    def _write(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except BlockingIOError:
            pass  # the host is not reading: a full buffer drops bytes, like a busy USB link
        except OSError:
            self._stop.set()

    def _reading(self, k: int) -> None:
        t = k / self.rate_hz
        m_ut, _ = self.scenario.field_ut(np.array([t]), np.array([k]))
        m = m_ut[0]
        g = self.scenario.orientation(np.array([t]))[0].T @ np.array([0.0, 0.0, GRAVITY_MS2])
        self.sent_field_ut.append(tuple(m))
        acc = [int(round(v * 8192 / GRAVITY_MS2)) for v in g]
        mag = [int(round(v * 10)) for v in m]
        self._emit("Raw:" + ",".join(str(v) for v in acc + [0, 0, 0] + mag))
        if self.uni:
            self._emit(
                "Uni:" + ",".join(f"{v:.2f}" for v in g) + ","
                + ",".join(f"{v:.4f}" for v in (0.0, 0.0, 0.0)) + ","
                + ",".join(f"{v:.2f}" for v in m)
            )
        self.readings += 1

    def _cal_lines(self, loop: int) -> None:
        if self.echo == "never":
            return
        half = self.cal_period // 2
        if loop % self.cal_period == half:
            v = self.accel_zerog + self.gyro_zerorate + self.mag_hardiron
            if self.echo == "wrong" and self.packets_stored:
                v = v[:6] + [v[6] + 0.5] + v[7:]
            self._emit("Cal1:" + ",".join(f"{x:.3f}" for x in v + [self.mag_field]))
        elif loop % self.cal_period == 0 and loop:
            self._emit("Cal2:" + ",".join(f"{x:.4f}" for x in self.mag_softiron))

    def _receive(self) -> None:
        try:
            while select.select([self.master], [], [], 0)[0]:
                chunk = os.read(self.master, 4096)
                if not chunk:
                    break
                if self.echo in ("never", "ignore"):
                    continue  # no packet handler: the bytes go nowhere
                self._rx += chunk
        except OSError:
            return
        while True:
            i = self._rx.find(mc.SIGNATURE)
            if i < 0:
                del self._rx[:-1]
                return
            del self._rx[:i]
            if len(self._rx) < mc.PACKET_LEN:
                return
            pkt = bytes(self._rx[: mc.PACKET_LEN])
            if mc.crc16(pkt) != 0:
                self.crc_failures += 1
                del self._rx[:2]  # look for another signature inside, as the sketch does
                continue
            del self._rx[: mc.PACKET_LEN]
            self._due.append((self._loop + self.store_delay_loops, struct.unpack("<16f", pkt[2:66])))

    def _store(self, f) -> None:
        self.accel_zerog = list(f[0:3])
        self.gyro_zerorate = list(f[3:6])
        self.mag_hardiron = list(f[6:9])
        self.mag_field = f[9]
        self.mag_softiron = [f[10], f[13], f[14], f[13], f[11], f[15], f[14], f[15], f[12]]
        self.packets_stored += 1
        self._emit("Wrote calibration")

    def _run(self) -> None:
        if self.banner:
            self._emit("Adafruit AHRS - IMU Calibration!")
            self._emit("Calibration filesys test")
            self._emit("No calibration loaded/found... will start with defaults")
        per_reading = (2 if self.uni else 1) / self.lines_per_s
        loop = 0
        t_next = time.monotonic()
        while not self._stop.is_set():
            self._reading(loop)
            loop += 1
            self._loop = loop
            self._receive()
            while self._due and self._due[0][0] <= loop:
                self._store(self._due.pop(0)[1])
            self._cal_lines(loop)
            t_next += per_reading
            delay = t_next - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -0.5:
                t_next = time.monotonic()
