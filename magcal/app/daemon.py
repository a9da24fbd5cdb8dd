"""``magcal run``: the long-running service that keeps one device calibrated.

The only loop in magcal with side effects. It owns the clock, the device, the state files,
signals and the status socket; the decisions it takes come from pure parts (``Session``,
``DriftMonitor``, the gates) and every one is logged (``logging``, logger ``magcal.daemon``).

    ┌──────────── connect (open, identify, read stored calibration, start) ◀─── back-off ◀──┐
    │                                                                                       │
    └▶ read ─▶ samples ─▶ session (collect) ─▶ drift monitor ─▶ (recalibrate: solve, gates, │
          │                                                   write, read back, compare)    │
          └─ port lost / stalled / replay ended ──────────────────────────────────────────┘

Faults it survives: the port vanishing (USB unplug: ``PortUnavailable``) or going silent
(``daemon.stall_s``), device resets (streaming is restarted), garbage and torn lines (the
framer counts them), a device that stops acknowledging (a write fails, streaming goes on), a
write echoed wrongly (not verified ⇒ not reported; the previous calibration is put back), a
full disk for captures or state (counted, logged, the data keeps flowing).

State survives a crash: every ``daemon.state_every_s`` the accumulated session, the monitor and
the counters are written through ``magcal.recordings.state.StateStore`` (atomic, checksummed, previous
good file kept); a restart resumes from them (on a ``replay://`` source, after the lines the
saved session already holds). SIGTERM/SIGINT stop cleanly (state written);
SIGHUP reloads the config file, keeping the old settings when the new ones are invalid. A local
UNIX socket ``status.sock`` in the state directory answers ``magcal status`` with one JSON
object; there is no network listener.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.calibration import Calibration
from ..core.errors import ConfigError, DeviceError, PortUnavailable, StateError
from ..core.events import Event
from ..core.sample import Sample
from ..devices import open_device as _open_device
from ..devices import scheme_of
from ..devices.base import Device
from ..logic.monitor import DriftMonitor
from ..logic.session import Session, Status
from ..recordings.capture import CaptureWriteError
from ..recordings.state import StateStore
from . import config
from .procedure import Outcome, write_and_verify

log = logging.getLogger("magcal.daemon")

READ_S = 0.1  # one read's wait
BATCH_S = 0.1  # a read that brought only a trickle waits out this much, so lines are taken in
BATCH_MIN = 16  # batches rather than one wake-up per line (100 Hz ⇒ ~10 wake-ups a second;
# measured with bench/daemon_soak.py --realtime 40: 1.7 % of one core at 0.1 s, 2.3 % at 0.05 s)
READY_EVERY = 100  # samples between gate checks while a recalibration waits for data
BASELINE_WINDOWS = 8  # monitor windows that learn the noise after a calibration is (re)loaded
SOCKET_NAME = "status.sock"
CAPTURE_NAME = "capture.cap"
DECISIONS_KEPT = 50
STATE_KIND = "magcal-daemon"
TAP_SCHEMES = ("sim", "emu", "replay", "serial")  # backends that take a capture tap (either dialect)


class Daemon:
    """One device, kept calibrated. ``run()`` blocks until ``request_stop()`` (or SIGTERM)."""

    def __init__(
        self,
        settings: config.Settings,
        *,
        state_dir: str | os.PathLike | None = None,
        config_path: str | None = None,
        overrides: dict | None = None,
        open_device: Callable[..., Device] = _open_device,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        sleep: Callable[[float], None] = time.sleep,
        on_sample: Callable[[int, Sample], None] | None = None,
        max_samples: int | None = None,
        device_options: dict | None = None,
    ):
        self.settings = settings
        self.config_path = config_path
        self.overrides = dict(overrides or {})
        self.state_dir = Path(state_dir or settings.daemon.state_dir).expanduser()
        self.store = StateStore(self.state_dir)
        self._open_device = open_device
        self._clock = clock
        self._wall = wall
        self._sleep = sleep
        self.on_sample = on_sample
        self.max_samples = max_samples
        self.device_options = dict(device_options or {})  # e.g. reply_timeout_s, for tests
        # what the state file carries
        self.generation = 0
        self.samples = 0  # valid samples collected (given to the session and the monitor)
        self.samples_in = 0  # every sample line received
        self.epoch = 0  # increases at every connection and every device reset
        self.last_seq: int | None = None
        self.replay_lines = 0  # sample lines taken from a replay:// source since its start
        self.faults: Counter = Counter()
        self.calibration: Calibration | None = None  # the one on the device, as last verified
        self.last_calibration: dict | None = None  # the last calibration this daemon wrote and verified
        self.recalibrations = 0
        self.session = Session(settings.gates, settings.model)
        self.monitor: DriftMonitor | None = None
        self.decisions: deque = deque(maxlen=DECISIONS_KEPT)
        # runtime only
        self.device: Device | None = None
        self.capture = None
        self.started_wall = self._wall()
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._retry = 0
        self._next_save = 0.0
        self._last_data = 0.0
        self._since_ready = 0
        self._skip_lines = 0  # a resumed replay: lines taken before the restart, read again from its start
        self._sock: socket.socket | None = None
        self.exit_reason = ""

    # -- decisions are logged and remembered -----------------------------------------------------
    def decide(self, what: str, level: int = logging.INFO, **detail) -> None:
        detail = {k: _plain(v) for k, v in detail.items() if v is not None}
        entry = {"t_utc": round(self._wall(), 3), "what": what, "at_sample": self.samples}
        entry.update(detail)
        self.decisions.append(entry)
        log.log(level, "%s%s (at sample %d)", what, "".join(f" {k}={v}" for k, v in detail.items()), self.samples)

    def request_stop(self) -> None:
        self._stop.set()

    def request_reload(self) -> None:
        self._reload.set()

    # -- the loop -----------------------------------------------------------------------------------
    def run(self) -> int:
        self._lock_state_dir()
        self._install_signals()
        self.resume()
        self._open_socket()
        self._open_capture()
        self.decide("daemon started", port=self.settings.port, state_dir=str(self.state_dir), pid=os.getpid())
        try:
            while not self._stop.is_set():
                if self._reload.is_set():
                    self._reload.clear()
                    self.reload()
                if self.device is None and not self._connect():
                    if self._clock() >= self._next_save:
                        self.save()  # the status file shows the outage too
                    self._wait(self._backoff())
                    continue
                self.step()
        finally:
            self._drain()
            self._disconnect("daemon stopping")
            self.decide("daemon stopped", reason=self.exit_reason or "requested")
            self.save(final=True)
            self._close_capture()
            self._close_socket()
            self._unlock_state_dir()
        return 0

    def step(self) -> None:
        """One read and everything it leads to."""
        t_read = self._clock()
        try:
            items = self.device.read(READ_S)
        except EOFError:
            self.exit_reason = "the recording ended"
            self.decide("source ended: stopping", port=self.settings.port)
            self._stop.set()
            return
        except CaptureWriteError as exc:
            self._capture_failed(exc)
            return
        except (DeviceError, OSError) as exc:
            self._lost(exc)
            return
        if items:
            try:
                self.handle(items)
            except (DeviceError, OSError) as exc:
                self._lost(exc)
                return
        now = self._clock()
        if now - self._last_data > self.settings.daemon.stall_s:  # no sample (events do not count)
            self.faults["stalls"] += 1
            self._lost(DeviceError(f"no data for {now - self._last_data:.1f} s (stall)"))
            return
        self._maybe_recalibrate()
        self._serve_socket()
        if now >= self._next_save:
            self.save()
        if self.max_samples is not None and self.samples >= self.max_samples:
            self.exit_reason = f"collected {self.samples} samples"
            self._stop.set()
        if 0 < len(items) < BATCH_MIN and not self._stop.is_set():
            rest = BATCH_S - (self._clock() - t_read)
            if rest > 0:
                self._sleep(rest)

    # -- connection -----------------------------------------------------------------------------
    def _backoff(self) -> float:
        d = self.settings.daemon
        return min(d.reconnect_max_s, d.reconnect_min_s * (2 ** min(self._retry - 1, 30)))

    def _wait(self, seconds: float) -> None:
        end = self._clock() + seconds
        while not self._stop.is_set():
            left = end - self._clock()
            if left <= 0:
                break
            self._serve_socket()
            if self._reload.is_set():
                break
            self._sleep(min(0.05, left))

    def _connect(self) -> bool:
        s = self.settings
        options = dict(self.device_options)
        if self.capture is not None and scheme_of(s.port) in TAP_SCHEMES:
            options["tap"] = self.capture
        if s.baud != 115200:
            options["baud"] = s.baud
        dev = None
        try:
            dev = self._open_device(s.port, dialect=s.dialect, **options)
            ident = dev.open()
            stored = self._read_stored(dev)
            dev.start(s.rate_hz)
        except (DeviceError, OSError, CaptureWriteError) as exc:
            if isinstance(exc, CaptureWriteError):
                self._capture_failed(exc)
            self._retry += 1
            self.faults["connect_failed"] += 1
            if dev is not None:
                _close_quietly(dev)
            self.decide("connect failed; retrying", logging.WARNING, port=s.port, error=str(exc),
                        retry_in_s=round(self._backoff(), 3))
            return False
        self.device = dev
        self.epoch += 1
        self.last_seq = None
        self._last_data = self._clock()
        self.decide("connected", port=s.port, firmware=ident.firmware or None, epoch=self.epoch,
                    stored_calibration="yes" if stored else "none")
        self._adopt(stored, dev)
        return True

    def _read_stored(self, dev: Device) -> Calibration | None:
        if not dev.can_store:
            return self.calibration  # a replay: keep monitoring what the state knew
        try:
            return dev.read_calibration()
        except DeviceError as exc:
            if isinstance(exc, PortUnavailable):
                raise
            self.decide("could not read the stored calibration", logging.WARNING, error=str(exc))
            return None

    def _adopt(self, stored: Calibration | None, dev: Device) -> None:
        """Monitor the calibration the device holds (keep the resumed monitor when it is the same)."""
        if stored is None:
            if self.calibration is not None:
                self.decide("device holds no calibration; monitoring stops", logging.WARNING)
            self.calibration = None
            self.monitor = None
            return
        same = self.calibration is not None and dev.matches(self.calibration, stored)
        if same and self.monitor is not None:
            return
        self.calibration = stored
        self._new_monitor("device calibration loaded" if not same else "monitor restarted")

    def _new_monitor(self, why: str) -> None:
        d = self.settings.daemon
        self.monitor = DriftMonitor(self.calibration, d.monitor_window, d.monitor_alpha, BASELINE_WINDOWS)
        self.decide(why + "; monitor learns the noise", windows=BASELINE_WINDOWS, window=d.monitor_window)

    def _drain(self) -> None:
        """Stopping: ask the device to stop streaming and take in what already arrived, so a
        clean stop leaves no received sample unprocessed. A replay has nothing in flight:
        reading on would only consume more of the recording, which a restart resumes from."""
        if self.device is None or getattr(self.device, "passive", False):
            return
        try:
            try:
                self.device.stop()
            except DeviceError as exc:
                if isinstance(exc, PortUnavailable):
                    return
            for _ in range(20):
                try:
                    items = self.device.read(0.02)
                except CaptureWriteError as exc:
                    self._capture_failed(exc)
                    continue
                if not items:
                    break
                self.handle(items)
        except (DeviceError, OSError, EOFError):
            pass

    def _capture_failed(self, exc: CaptureWriteError) -> None:
        self.faults["capture_failed"] += 1
        self.decide("capture stopped; streaming continues", logging.ERROR, error=str(exc))

    def _lost(self, exc: Exception) -> None:
        kind = "port_lost" if isinstance(exc, (PortUnavailable, OSError)) else "link_error"
        self.faults[kind] += 1
        self._retry = max(self._retry, 1)
        self._disconnect(f"link lost: {exc}")

    def _disconnect(self, why: str) -> None:
        if self.device is None:
            return
        dev, self.device = self.device, None
        _close_quietly(dev)
        self.decide("disconnected", logging.WARNING if "lost" in why else logging.INFO, why=why)

    # -- data -------------------------------------------------------------------------------------
    def handle(self, items) -> None:
        fields, temps = [], []
        replay = scheme_of(self.settings.port) == "replay"
        for item in items:
            if self._skip_lines:
                # already in the resumed session: neither its samples nor its events count again
                self._skip_lines -= int(isinstance(item, Sample))
                continue
            if replay and isinstance(item, Sample):
                self.replay_lines += 1
            if isinstance(item, Event):
                self._event(item)
                self.session.add(item)
                continue
            if not isinstance(item, Sample):
                continue
            self.samples_in += 1
            self._last_data = self._clock()
            self._retry = 0
            if self.last_seq is not None and item.seq == self.last_seq:
                self.faults["duplicate_lines"] += 1  # never expected; counted to prove it
                continue
            self.last_seq = item.seq
            if not item.valid or item.aux.get("calibrated"):
                self.session.add(item)  # counted there as rejected
                continue
            self.session.add(item)
            self.samples += 1
            self._since_ready += 1
            fields.append(item.field_ut)
            temps.append(np.nan if item.temp_c is None else item.temp_c)
            if self.on_sample is not None:
                self.on_sample(self.epoch, item)
        if fields and self.monitor is not None:
            for v in self.monitor.add(np.asarray(fields), np.asarray(temps)):
                self._verdict(v)

    def _event(self, ev: Event) -> None:
        if ev.kind == "gap":
            self.faults["gaps"] += 1
            self.faults["lost_lines"] += ev.count
        elif ev.kind == "reset":
            self.faults["device_resets"] += 1
            self.epoch += 1
            self.last_seq = None
            self.decide("device reset itself; restarting the stream", logging.WARNING, epoch=self.epoch)
            self.device.start(self.settings.rate_hz)

    def _verdict(self, v) -> None:
        if v.phase == "baseline":
            if self.monitor.phase == "test":
                sigma, tau = self.monitor.noise()
                self.decide("monitor baseline done", noise_ut=round(sigma, 4), autocorrelation=round(tau, 2))
            return
        if not v.drifted:
            log.debug("window %d fits (p=%.3g)", v.window, v.p_value)
            return
        first = self.monitor.alarms == 1
        self.faults["drift_alarms"] += 1
        if not first:
            log.debug("window %d: still drifted (p=%.3g)", v.window, v.p_value)
            return
        self.decide(
            "calibration no longer fits the data",
            logging.WARNING,
            window=v.window, statistic=round(v.statistic, 2), threshold=round(v.threshold, 2), df=v.df,
            p_value=float(f"{v.p_value:.3g}"), shift_ut=[round(x, 2) for x in v.estimated_shift_ut],
        )
        # the samples collected so far belong to the old magnetic environment
        self.session = Session(self.settings.gates, self.settings.model)
        self._since_ready = 0
        if self._may_write():
            self.decide("collecting for a recalibration")
        else:
            self.decide("recalibration disabled (daemon.recalibrate: false); reporting only")

    # -- recalibration ----------------------------------------------------------------------------
    def _may_write(self) -> bool:
        s = self.settings
        return bool(s.daemon.recalibrate and s.write and self.device is not None and self.device.can_store)

    def _wants_calibration(self) -> bool:
        return self.calibration is None or (self.monitor is not None and self.monitor.drifted)

    def _maybe_recalibrate(self) -> None:
        if self._since_ready < READY_EVERY or not self._may_write() or not self._wants_calibration():
            return
        self._since_ready = 0
        if not self.session.ready():
            return
        session = self.session
        self.session = Session(self.settings.gates, self.settings.model)
        self.decide("gates pass on the live estimate: solving", samples=len(session.kept),
                    coverage=round(session.kept.coverage(), 3))
        result = session.solve()
        if session.status is Status.FAILED:
            self.faults["gate_failed"] += 1
            self.decide("recalibration refused", logging.WARNING, failure=session.failure,
                        message=session.failure_message)
            return
        outcome = Outcome(session=session, identity=self.device.identity)
        try:
            outcome = write_and_verify(self.device, session, outcome)
        except DeviceError as exc:  # anything write_and_verify did not turn into a failure
            session.fail("write_failed", str(exc))
        if session.status is Status.DONE and outcome.verified:
            self.calibration = outcome.stored
            self.recalibrations += 1
            self.last_calibration = {
                "calibration": outcome.stored.to_dict(),
                "written_utc": round(self._wall(), 3),
                "verified": True,
                "rms_ut": float(result.rms_ut),
                "samples": len(session.kept),
                "coverage": round(session.kept.coverage(), 4),
            }
            self.decide("calibration written and verified by read-back",
                        offset_ut=[round(x, 3) for x in outcome.stored.offset_ut],
                        field_ut=round(outcome.stored.field_ut, 3), rms_ut=round(float(result.rms_ut), 3))
            self._new_monitor("new calibration")
            self.save()
            return
        self.faults[session.failure or "write_failed"] += 1
        self.decide("calibration NOT written", logging.ERROR, failure=session.failure,
                    message=session.failure_message, previous_restored=outcome.restored)
        self._recheck_device_record()

    def _recheck_device_record(self) -> None:
        """After a failed write: is what the device holds still the calibration we monitor?"""
        try:
            held = self.device.read_calibration()
        except DeviceError as exc:
            self.decide("could not re-read the device's calibration", logging.WARNING, error=str(exc))
            return
        if held is None and self.calibration is None:
            return
        if held is not None and self.calibration is not None and self.device.matches(self.calibration, held):
            return
        self.faults["device_record_unverified"] += 1
        self.decide("the device holds a record this daemon did not verify; monitoring the verified one",
                    logging.ERROR)

    # -- config reload ------------------------------------------------------------------------------
    def reload(self) -> None:
        try:
            new = config.load(self.config_path, self.overrides)
        except ConfigError as exc:
            self.faults["config_rejected"] += 1
            self.decide("config reload rejected; keeping the old settings", logging.ERROR, error=str(exc))
            return
        old, self.settings = self.settings, new
        self.decide("config reloaded", config=self.config_path)
        if (old.port, old.dialect, old.baud, old.rate_hz) != (new.port, new.dialect, new.baud, new.rate_hz):
            self._disconnect("settings changed: reconnecting")
        if old.port != new.port:  # another device: nothing collected so far belongs to it
            self.session = Session(new.gates, new.model)
            self.monitor, self.calibration = None, None
        else:  # the samples stay; the new gates and model judge them
            self.session.gates_cfg, self.session.model = new.gates, new.model
        if self.calibration is not None and (old.daemon.monitor_window, old.daemon.monitor_alpha) != (
            new.daemon.monitor_window, new.daemon.monitor_alpha
        ):
            self._new_monitor("monitor settings changed")

    # -- state ---------------------------------------------------------------------------------------
    def status(self) -> dict:
        s = self.session
        return {
            "running": not self._stop.is_set(),
            "pid": os.getpid(),
            "port": self.settings.port,
            "connected": self.device is not None,
            "device": self.device.identity.to_dict() if self.device is not None and self.device.identity else None,
            "uptime_s": round(self._wall() - self.started_wall, 3),
            "samples": self.samples,
            "samples_in": self.samples_in,
            "epoch": self.epoch,
            "last_seq": self.last_seq,
            "coverage": round(s.kept.coverage(), 4),
            "session": s.progress(),
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
            "last_calibration": self.last_calibration,
            "recalibrations": self.recalibrations,
            "monitor": None if self.monitor is None else self.monitor.status(),
            "faults": dict(sorted(self.faults.items())),
            "link": self.device.stats() if self.device is not None else {},
            "capture": None if self.capture is None else self.capture.stats(),
            "decisions": list(self.decisions)[-10:],
        }

    def payload(self) -> dict:
        return {
            "kind": STATE_KIND,
            "generation": self.generation,
            "saved_utc": round(self._wall(), 3),
            "status": self.status(),
            "resume": {
                "port": self.settings.port,
                "samples": self.samples,
                "samples_in": self.samples_in,
                "replay_lines": self.replay_lines,
                "epoch": self.epoch,
                "faults": dict(self.faults),
                "calibration": None if self.calibration is None else self.calibration.to_dict(),
                "last_calibration": self.last_calibration,
                "recalibrations": self.recalibrations,
                "session": self.session.to_state(),
                "monitor": None if self.monitor is None else self.monitor.to_state(),
                "decisions": list(self.decisions),
            },
        }

    def save(self, final: bool = False) -> bool:
        self._next_save = self._clock() + self.settings.daemon.state_every_s
        self.generation += 1
        try:
            data = self.payload()
            if final:
                data["status"]["running"] = False
            self.store.save(data)
        except (OSError, StateError) as exc:
            self.faults["state_write_failed"] += 1
            self.decide("state not written", logging.ERROR, error=str(exc))
            return False
        return True

    def resume(self) -> None:
        try:
            data = self.store.load()
        except StateError as exc:
            self.faults["state_refused"] += 1
            self.decide("state refused; starting fresh", logging.ERROR, error=str(exc))
            return
        if data is None:
            self.decide("no previous state; starting fresh")
            return
        try:
            if data.get("kind") != STATE_KIND:
                raise ValueError(f"state kind is {data.get('kind')!r}, not {STATE_KIND!r}")
            r = data["resume"]
            session = Session.from_state(r["session"], self.settings.gates)
            monitor = DriftMonitor.from_state(r["monitor"]) if r["monitor"] else None
            cal = Calibration.from_dict(r["calibration"]) if r["calibration"] else None
            generation = int(data["generation"])
            counts = (int(r["samples"]), int(r["samples_in"]), int(r["epoch"]), int(r["recalibrations"]))
            replay_lines = int(r.get("replay_lines", 0))
            faults = Counter({str(k): int(v) for k, v in r["faults"].items()})
        except (KeyError, TypeError, ValueError) as exc:
            self.faults["state_refused"] += 1
            self.decide("state unusable; starting fresh", logging.ERROR, error=str(exc))
            return
        if r.get("port") != self.settings.port:
            # another device's samples and calibration must not be mixed into this one's
            self.decide("state was written for another port; keeping its counters only", logging.WARNING,
                        state_port=r.get("port"), port=self.settings.port)
            session, monitor, cal = Session(self.settings.gates, self.settings.model), None, None
            r = dict(r, last_calibration=None)
            replay_lines = 0
        self.session, self.monitor, self.calibration = session, monitor, cal
        self.generation = generation
        self.samples, self.samples_in, self.epoch, self.recalibrations = counts
        self.faults = faults
        self.last_calibration = r.get("last_calibration")
        self.decisions.extend(r.get("decisions", []))
        self.decide("resumed", generation=generation, samples=self.samples, note=self.store.last_load_note)
        if replay_lines and scheme_of(self.settings.port) == "replay":
            # a replay is read from its start again: the lines the saved session already holds
            # are skipped, not counted twice
            self.replay_lines = self._skip_lines = replay_lines
            self.decide("replay resumes after the lines already taken", skipped_lines=replay_lines)

    # -- capture --------------------------------------------------------------------------------------
    def _open_capture(self) -> None:
        limit = self.settings.daemon.capture_max_bytes
        if not limit:
            return
        from ..recordings.capture import CaptureWriter, make_header, roll_keep_one

        path = self.state_dir / CAPTURE_NAME
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            # two files (current and .1) of half the bound each: the total stays within it
            header = make_header(self.settings.port, self.settings.baud, self.settings.dialect or "native")
            self.capture = CaptureWriter(path, header, max_bytes=max(4096, limit // 2), on_full=roll_keep_one)
        except (CaptureWriteError, OSError, ValueError) as exc:
            self.faults["capture_failed"] += 1
            self.decide("capture not started; streaming without it", logging.ERROR, error=str(exc))
            self.capture = None
            return
        self.decide("rolling capture", path=str(path), max_bytes=limit)

    def _close_capture(self) -> None:
        if self.capture is not None:
            self.capture.close()

    # -- one daemon per state directory ---------------------------------------------------------
    def _lock_state_dir(self) -> None:
        """An exclusive lock on ``state_dir/lock`` for the daemon's lifetime (released by the
        kernel even after kill -9): two daemons must never write one state."""
        self._lock_fd = None
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock
            return
        self.state_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.state_dir / "lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise StateError(f"another magcal daemon is running on {self.state_dir}") from None
        self._lock_fd = fd

    def _unlock_state_dir(self) -> None:
        if getattr(self, "_lock_fd", None) is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # -- signals and the status socket ------------------------------------------------------------
    def _install_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        signal.signal(signal.SIGTERM, lambda *_: self.request_stop())
        signal.signal(signal.SIGINT, lambda *_: self.request_stop())
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, lambda *_: self.request_reload())

    def _open_socket(self) -> None:
        if not self.settings.daemon.socket or not hasattr(socket, "AF_UNIX"):
            return
        path = self.state_dir / SOCKET_NAME
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            if path.exists() or path.is_symlink():
                path.unlink()
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.bind(str(path))
            os.chmod(path, 0o660)
            sock.listen(4)
            sock.setblocking(False)
        except OSError as exc:
            self.decide("status socket unavailable; the state file still answers", logging.WARNING,
                        error=str(exc))
            return
        self._sock = sock

    def _serve_socket(self) -> None:
        if self._sock is None:
            return
        while True:
            try:
                conn, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            try:
                conn.settimeout(1.0)
                conn.sendall(json.dumps(self.status(), allow_nan=False, default=_json_default).encode() + b"\n")
            except (OSError, ValueError):
                pass
            finally:
                conn.close()

    def _close_socket(self) -> None:
        if self._sock is None:
            return
        self._sock.close()
        self._sock = None
        try:
            (self.state_dir / SOCKET_NAME).unlink()
        except OSError:
            pass


def _plain(v):
    """numpy scalars and arrays → Python numbers and lists (for logs and JSON)."""
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    return v


def _close_quietly(dev: Device) -> None:
    try:
        dev.close()
    except (DeviceError, OSError):
        pass


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def query_socket(state_dir, timeout_s: float = 2.0) -> dict | None:
    """The live status from a running daemon's socket; None when nobody answers."""
    path = Path(state_dir).expanduser() / SOCKET_NAME
    if not hasattr(socket, "AF_UNIX") or not path.exists():
        return None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
        chunks = []
        while True:
            b = s.recv(65536)
            if not b:
                break
            chunks.append(b)
    except OSError:
        return None
    finally:
        s.close()
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        return None
