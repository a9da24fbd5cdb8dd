"""The calibration session: a state machine with no I/O.

    COLLECTING ──ready()──▶ SOLVING ──fit ok, gates pass──▶ WRITING ──stored──▶ VERIFYING ──▶ DONE
         │                     │                               │                    │
         └───── fail(failure) ─┴───────────────────────────────┴────────────────────┴──▶ FAILED

Every change of state goes through ``_set_status``, which refuses transitions the diagram does
not have. Lifecycle (``status``) and failure reasons (``failure``) are separate: a FAILED
session says *why* in ``failure`` (a ``logic.failures.Failure``: the reason, and the gate when
a gate refused) and ``failure_message`` (a sentence).

The session takes samples and link events and keeps three things: the tracker
(``fit.tracker``: the calibration in force so far, the live estimate shown and judged while
collecting), the streaming sphere accumulator (every valid sample, O(1): its normal-matrix
condition is the coverage gate), and the bounded direction-balanced sample buffer
(``fit.cell_buffer``, first come first kept: ``WhenFull.REFUSE``) for the final
maximum-likelihood fit. Gates are data (``GateResult``), evaluated on the live estimate while
collecting and on the final fit before anything is written.
"""

from __future__ import annotations

from collections import Counter
from enum import Enum

import numpy as np

from ..core.calibration import Calibration
from ..core.events import Event
from ..core.sample import Sample
from ..fit import SphereAccumulator, fit_calibration
from ..fit.cell_buffer import CellBuffer, WhenFull
from ..fit.tracker import Tracker
from . import failures
from .failures import Failure
from .gates import Clearance, Evidence, GateResult, Gates, clear_for_write, data_gates, model_gates

ESTIMATE_EVERY = 50  # samples between live re-solves (cheap: a 4×4 solve)
RECENTRE_UT = 2.0  # re-bin the kept samples when the centre estimate moves this much


class Status(str, Enum):
    COLLECTING = "collecting"
    SOLVING = "solving"
    WRITING = "writing"
    VERIFYING = "verifying"
    DONE = "done"
    FAILED = "failed"


_ALLOWED = {
    Status.COLLECTING: {Status.SOLVING, Status.FAILED},
    Status.SOLVING: {Status.WRITING, Status.DONE, Status.COLLECTING, Status.FAILED},
    Status.WRITING: {Status.VERIFYING, Status.FAILED},
    Status.VERIFYING: {Status.DONE, Status.FAILED},
    Status.DONE: set(),
    Status.FAILED: set(),
}


class Session:
    def __init__(self, gates: Gates | None = None, model: str = "auto"):
        self.gates_cfg = gates or Gates()
        self.model = model
        self.status = Status.COLLECTING
        self.failure: Failure | None = None
        self.failure_message = ""
        self.counters: Counter = Counter()
        self.accumulator = SphereAccumulator()
        self.tracker = Tracker()  # the live estimate: the calibration in force so far
        self.kept = CellBuffer(when_full=WhenFull.REFUSE, centre_ut=np.zeros(3))
        self.estimate = None  # the accumulator's SphereFit | FitFailure | None (the coverage test)
        self.result = None  # the final FitResult once solved
        self.final_gates: list[GateResult] = []  # the gates as judged on the final fit
        self.clearance: Clearance | None = None  # the decision on writing the final fit
        self.history: list[tuple[str, str]] = []
        self._since_estimate = 0
        self._ready = False  # every gate passed at the last check: later samples are not taken
        self._last_seq: int | None = None
        self.last_field_ut = None  # the latest valid sample (µT): where the board points now
        self.last_sample = None  # that sample whole (its time, and an accelerometer in aux when sent)

    # -- the one choke point -------------------------------------------------------------------
    def _set_status(self, new: Status, failure: Failure | None = None, message: str = "") -> None:
        if new not in _ALLOWED[self.status]:
            raise RuntimeError(f"session cannot go from {self.status.value} to {new.value}")
        self.history.append((self.status.value, new.value))
        self.status = new
        if new is Status.FAILED:
            self.failure = failure
            self.failure_message = message

    def retune(self, gates: Gates, model: str) -> None:
        """New gates and model judge the samples collected so far (a settings reload)."""
        self.gates_cfg, self.model = gates, model

    def fail(self, failure: Failure, message: str) -> None:
        if not isinstance(failure, Failure):
            raise TypeError(f"a session fails with a Failure (magcal.logic.failures), not {failure!r}")
        if self.status not in (Status.DONE, Status.FAILED):
            self._set_status(Status.FAILED, failure, message)

    # -- collecting ----------------------------------------------------------------------------
    def add(self, item) -> None:
        if self.status is not Status.COLLECTING:
            self.counters["ignored_after_collecting"] += 1
            return
        if isinstance(item, Event):
            self.counters[f"event_{item.kind}"] += 1
            if item.kind == "gap":
                self.counters["lost_samples"] += item.count
            return
        if not isinstance(item, Sample):
            return
        if self._ready:  # the data are complete; what comes later does not change the result
            self.counters["after_ready"] += 1
            return
        self.counters["samples_in"] += 1
        if not item.valid:
            self.counters["rejected_flagged"] += 1
            return
        if item.aux.get("calibrated"):
            self.counters["rejected_calibrated"] += 1
            return
        m = np.asarray(item.field_ut, dtype=np.float64)
        if not np.all(np.isfinite(m)):
            self.counters["rejected_nonfinite"] += 1
            return
        self.accumulator.add(m)
        self.last_field_ut = m
        self.last_sample = item
        self.tracker.add(m, item.t_s)
        self.kept.add(float(m[0]), float(m[1]), float(m[2]), float(item.t_s))
        self._since_estimate += 1
        if self._since_estimate >= ESTIMATE_EVERY:
            self.update_estimate()
            # Judged at fixed sample counts, not whenever the caller looks, so the samples a
            # calibration uses do not depend on how reads happened to be chunked: a replay of
            # a capture calibrates from exactly the samples the live run used.
            self._ready = all(r.passed for r in self.live_gates())

    def add_many(self, items) -> None:
        for item in items:
            self.add(item)

    def update_estimate(self):
        self._since_estimate = 0
        est = self.accumulator.solve()
        self.estimate = est
        if est and np.linalg.norm(est.offset_ut - self.kept.centre_ut) > RECENTRE_UT:
            self.kept.rebin(est.offset_ut, force=True)
        return est

    # -- gates -----------------------------------------------------------------------------------
    def live_gates(self) -> list[GateResult]:
        g = self.gates_cfg
        est = self.estimate
        out = data_gates(g, len(self.kept), self.kept.coverage(), float(est.condition) if est else None)
        if not est:
            why = "no estimate yet" if est is None else est.message
            return out[:2] + [GateResult("solvable", False, None, None, why)]
        live = self.tracker.estimate
        if live is None:
            return out + [GateResult("solvable", False, None, None, "the tracker has no calibration yet")]
        c = live.calibration
        return out + model_gates(g, c.offset_ut, c.field_ut, live.noise_ut, live.offset_sigma_ut)

    def ready(self) -> bool:
        return self.status is Status.COLLECTING and self._ready

    def failing_gates(self) -> list[GateResult]:
        return [r for r in self.live_gates() if not r.passed]

    def progress(self) -> dict:
        """Where collecting stands; the live calibration is the tracker's (``fit.tracker``)."""
        live = self.tracker.estimate
        c = live.calibration if live is not None else None
        return {
            "status": self.status.value,
            "samples": int(self.counters["samples_in"]),
            "kept": len(self.kept),
            "coverage": self.kept.coverage(),
            "model": live.model if live is not None else None,
            "offset_ut": [float(v) for v in c.offset_ut] if c is not None else None,
            "field_ut": float(c.field_ut) if c is not None else None,
        }

    # -- solving ---------------------------------------------------------------------------------
    def solve(self):
        """Final fit on the kept samples; on success the session moves to WRITING's doorstep.

        Returns the FitResult, or the failure (and the session is FAILED)."""
        self._set_status(Status.SOLVING)
        self.update_estimate()
        result = fit_calibration(self.kept.field_ut, model=self.model, outliers=True)
        if not result:
            self.fail(failures.FIT_FAILED, f"the fit failed: {result.message}")
            return result
        self.clearance = clear_for_write(self.gates_cfg, self.evidence(result))
        self.final_gates = list(self.clearance.results)
        self.result = result
        failing = self.clearance.blocking  # a gate without its evidence blocks as a failing one does
        if failing:
            self.fail(Failure.of_gate(failing[0].name), "final fit fails gate: " + "; ".join(r.message for r in failing))
        return result

    def evidence(self, result) -> Evidence:
        """What the final fit and the kept samples show, for the gates."""
        cal = result.calibration
        est = self.estimate
        return Evidence(offset_ut=tuple(float(v) for v in cal.offset_ut), field_ut=float(cal.field_ut),
                        rms_ut=float(result.rms_ut),
                        offset_sigma_ut=tuple(float(v) for v in result.uncertainty["offset_ut"]),
                        n_used=len(self.kept), coverage=self.kept.coverage(),
                        condition=float(est.condition) if est else None)

    def begin_write(self) -> None:
        self._set_status(Status.WRITING)

    def written(self) -> None:
        self._set_status(Status.VERIFYING)

    def verified(self, ok: bool, message: str = "") -> None:
        if ok:
            self._set_status(Status.DONE)
        else:
            self.fail(failures.VERIFY_MISMATCH, message or "the calibration read back differs from the one sent")

    def finish_without_write(self) -> None:
        self._set_status(Status.DONE)

    @property
    def calibration(self) -> Calibration | None:
        return self.result.calibration if self.result else None

    # -- persistence (the daemon resumes a collecting session after a restart) -------------------
    def to_state(self) -> dict:
        """JSON-able state of a COLLECTING session (later stages are not resumed: they are
        re-run from the collected samples). The live estimate is recomputed on load."""
        if self.status is not Status.COLLECTING:
            raise RuntimeError(f"only a collecting session is saved, not one that is {self.status.value}")
        return {
            "model": self.model,
            "counters": {k: int(v) for k, v in self.counters.items()},
            "accumulator": self.accumulator.to_state(),
            "kept": self.kept.to_state(),
            "tracker": self.tracker.to_state(),
        }

    @classmethod
    def from_state(cls, d: dict, gates: Gates | None = None) -> "Session":
        """Rebuild a collecting session; ValueError when ``d`` is malformed."""
        try:
            s = cls(gates, d["model"])
            s.counters = Counter({str(k): int(v) for k, v in d["counters"].items()})
            s.accumulator = SphereAccumulator.from_state(d["accumulator"])
            s.kept = CellBuffer.from_state(d["kept"])
            if "tracker" in d:  # (states written before the tracker start a fresh one)
                s.tracker = Tracker.from_state(d["tracker"])
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"session state is malformed: {exc!r}") from None
        if s.accumulator.n:
            s.update_estimate()
        return s
