"""The drift watcher: the calibration the device holds (as last verified) and the monitor that
tests, window by window, whether it still fits the data (``magcal.logic.monitor``)."""

from __future__ import annotations

import logging
from collections import Counter
from typing import Callable

import numpy as np

from ...core.calibration import Calibration
from ...logic.monitor import DriftMonitor, Phase
from .journal import Decision, Journal

log = logging.getLogger("magcal.daemon")

BASELINE_WINDOWS = 8  # monitor windows that learn the noise after a calibration is (re)loaded


class DriftWatcher:
    def __init__(self, daemon_settings, journal: Journal, faults: Counter):
        self.settings = daemon_settings  # the ``daemon:`` section: monitor_window, monitor_alpha
        self._journal = journal
        self._faults = faults
        self.calibration: Calibration | None = None  # the one on the device, as last verified
        self.monitor: DriftMonitor | None = None

    @property
    def wants_calibration(self) -> bool:
        """None is held, or the one held no longer fits."""
        return self.calibration is None or (self.monitor is not None and self.monitor.drifted)

    def watch(self, calibration: Calibration, because: Decision) -> None:
        """Monitor ``calibration`` from now on; the monitor first learns the noise."""
        d = self.settings
        self.calibration = calibration
        self.monitor = DriftMonitor(calibration, d.monitor_window, d.monitor_alpha, BASELINE_WINDOWS)
        self._journal.record(because, windows=BASELINE_WINDOWS, window=d.monitor_window)

    def adopt(self, stored: Calibration | None, same: Callable[[Calibration, Calibration], bool]) -> None:
        """Connected: monitor what the device holds (``same``: the device's own comparison). The
        resumed monitor is kept when the device holds the calibration it was watching."""
        if stored is None:
            if self.calibration is not None:
                self._journal.record(Decision.NOTHING_STORED)
            self.forget()
            return
        held = self.calibration is not None and same(self.calibration, stored)
        if held and self.monitor is not None:
            return
        self.watch(stored, Decision.MONITOR_RESTARTED if held else Decision.CALIBRATION_LOADED)

    def forget(self) -> None:
        self.calibration, self.monitor = None, None

    def add(self, fields_ut, temps_c) -> bool:
        """Samples for the monitor; True when this calibration's first alarm just rang."""
        if self.monitor is None:
            return False
        rang = False
        for v in self.monitor.add(np.asarray(fields_ut), np.asarray(temps_c)):
            rang = self._verdict(v) or rang
        return rang

    def _verdict(self, v) -> bool:
        if v.phase is Phase.BASELINE:
            if self.monitor.phase is Phase.TEST:
                sigma, tau = self.monitor.noise()
                self._journal.record(Decision.BASELINE_DONE, noise_ut=round(sigma, 4), autocorrelation=round(tau, 2))
            return False
        if not v.drifted:
            log.debug("window %d fits (p=%.3g)", v.window, v.p_value)
            return False
        self._faults["drift_alarms"] += 1
        if self.monitor.alarms != 1:
            log.debug("window %d: still drifted (p=%.3g)", v.window, v.p_value)
            return False
        self._journal.record(
            Decision.DRIFTED,
            window=v.window, statistic=round(v.statistic, 2), threshold=round(v.threshold, 2), df=v.df,
            p_value=float(f"{v.p_value:.3g}"), shift_ut=[round(x, 2) for x in v.estimated_shift_ut],
        )
        return True

    def retune(self, daemon_settings) -> None:
        """New settings: a new monitor when its window or level changed."""
        old, self.settings = self.settings, daemon_settings
        changed = (old.monitor_window, old.monitor_alpha) != (daemon_settings.monitor_window,
                                                               daemon_settings.monitor_alpha)
        if changed and self.calibration is not None:
            self.watch(self.calibration, Decision.MONITOR_RETUNED)

    def status(self) -> dict:
        return {"calibration": None if self.calibration is None else self.calibration.to_dict(),
                "monitor": None if self.monitor is None else self.monitor.status()}

    def to_state(self) -> dict:
        return {"calibration": None if self.calibration is None else self.calibration.to_dict(),
                "monitor": None if self.monitor is None else self.monitor.to_state()}

    def restore(self, calibration: Calibration | None, monitor: DriftMonitor | None) -> None:
        self.calibration, self.monitor = calibration, monitor
