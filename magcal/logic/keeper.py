"""Keeping a device calibrated: when is the tracker's calibration worth an EEPROM write?

The tracker (``fit.tracker``) follows the calibration as the sensor wanders; the device holds
the one written last. ``Keeper.decide`` says whether to write the tracker's now — a typed
``WriteDecision`` — and never says yes past a gate:

1. the tracker has a calibration, and it passes the gates every written calibration passes
   (``gates.model_gates``: field range, offset size, residual, offset uncertainty) plus the
   memory's own: enough samples and enough directions (``min_samples``, ``min_coverage``);
2. it is better than the device's by more than chance: ``tracker.compare`` judges both on the
   tracker's memory, cell by cell, and the gain must reach z ≥ z(α) (one-sided; α the drift
   monitor's false-alarm probability) — a device holding no calibration needs no such test;
3. the EEPROM budget allows a write;
4. and then the calibration as it may be reported (``fit.tracker_check.checked``: a model fit's
   gates accept on the tracker's memory, every σ at least fit's there) passes 1–3 again.

**The budget.** The calibration record lives in the ATmega328P's EEPROM, rated for 100 000
write/erase cycles per cell. Every write rewrites the same record, so every write counts. The
keeper spends writes from a token bucket: ``per_day`` on average (default 24, one an hour —
8 760 a year, 11 years to the rated endurance at the most the budget allows) with at most
``burst`` back to back (default 3, so a new payload can be followed by a couple of writes as the
tracker settles). A write that had to be undone (``procedure.write_verified`` puts the previous
record back, or erases the failed one) costs two cycles; the caller reports what it spent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

from scipy.special import ndtri

from ..core.calibration import Calibration
from ..core.errors import ConfigError
from ..fit.tracker import Comparison, Estimate, Tracker, compare
from ..fit.tracker_check import checked
from .gates import GateResult, Gates, model_gates

EEPROM_RATED_CYCLES = 100_000  # ATmega328P datasheet: EEPROM write/erase endurance per cell
DAY_S = 86400.0
RECHECK_SAMPLES = 3000  # after fit's check refused the tracker's calibration, samples before it is asked again


@dataclass(frozen=True)
class Budget:
    """How many EEPROM writes the keeper may spend: ``per_day`` on average, ``burst`` at once."""

    per_day: float = 24.0
    burst: int = 3

    def check(self) -> None:
        if not self.per_day > 0 or self.burst < 1:
            raise ConfigError(f"the write budget needs per_day > 0 and burst ≥ 1, got {self.per_day}, {self.burst}")

    @property
    def years_to_rated_endurance(self) -> float:
        return EEPROM_RATED_CYCLES / (self.per_day * 365.25)


class DecisionReason(str, Enum):
    """Why a keeper's ``WriteDecision`` writes or holds (the value is the ``reason`` a journal and JSON carry)."""

    NO_CALIBRATION = "no_calibration"  # the tracker has none yet
    GATE = "gate"  # a gate fails
    NOT_SIGNIFICANT = "not_significant"  # not better than the device's by more than chance
    BUDGET = "budget"  # better, but the EEPROM budget is spent for now
    FIRST = "first"  # write: the device holds no calibration
    BETTER = "better"  # write: significantly better than the device's


@dataclass(frozen=True)
class WriteDecision:
    write: bool
    reason: DecisionReason
    calibration: Calibration | None = None
    comparison: Comparison | None = None
    gates: tuple[GateResult, ...] = field(default_factory=tuple)
    message: str = ""
    estimate: Estimate | None = field(default=None, repr=False)  # a write's: the checked estimate (its σ)

    def to_dict(self) -> dict:
        return {"write": self.write, "reason": self.reason.value, "message": self.message,
                "calibration": None if self.calibration is None else self.calibration.to_dict(),
                "comparison": None if self.comparison is None else self.comparison.to_dict(),
                "gates": [g.to_dict() for g in self.gates if not g.passed]}


class Keeper:
    """The tracker, the gates and the EEPROM budget of one device; no I/O."""

    def __init__(self, gates: Gates, budget: Budget | None = None, alpha: float = 0.001, now_s: float = 0.0,
                 tracker: Tracker | None = None):
        self.gates = gates
        self.budget = budget or Budget()
        self.budget.check()
        if not 0 < alpha < 0.5:
            raise ConfigError(f"the keeper's significance level must be in (0, 0.5), got {alpha}")
        self.z_needed = float(ndtri(1.0 - alpha))
        self.tracker = tracker or Tracker()
        self.tokens = float(self.budget.burst)
        self.refilled_s = float(now_s)
        self.cycles = 0  # EEPROM write cycles spent (writes, and restores after a failed write)
        self.writes = 0  # writes that were verified by read-back
        self.failed = 0  # writes that were not
        self._held: tuple[int, WriteDecision] | None = None  # (tracker.n, the decision) of a refused check

    def add(self, m_ut, t_s: float):
        """One sample for the tracker; returns its change of calibration, if any."""
        return self.tracker.add(m_ut, t_s)

    def restart(self) -> None:
        """The field changed at once (the drift monitor rang: a payload, a magnet): what the
        tracker remembers belongs to the old one, so it starts afresh. The tracker follows
        gradual wander by itself; a step it would take for outliers. The budget stays: it is
        the EEPROM's."""
        self.tracker = Tracker(self.tracker.config)
        self._held = None

    def _refill(self, now_s: float) -> None:
        dt = max(float(now_s) - self.refilled_s, 0.0)
        self.tokens = min(float(self.budget.burst), self.tokens + dt * self.budget.per_day / DAY_S)
        self.refilled_s = max(self.refilled_s, float(now_s))

    def _gates(self, est) -> list[GateResult]:
        g = self.gates
        n, cov = int(self.tracker.memory.valid.sum()), self.tracker.coverage()
        out = [GateResult("min_samples", n >= g.min_samples, float(n), g.min_samples,
                          f"{n} samples in memory ({g.min_samples} needed)"),
               GateResult("min_coverage", cov >= g.min_coverage, cov, g.min_coverage,
                          f"{100 * cov:.0f}% of directions in memory, {100 * g.min_coverage:.0f}% needed")]
        c = est.calibration
        return out + model_gates(g, c.offset_ut, c.field_ut, est.noise_ut, est.offset_sigma_ut)

    def decide(self, device: Calibration | None, now_s: float) -> WriteDecision:
        """Write the tracker's calibration over ``device``'s (None: the device holds none)?"""
        self._refill(now_s)
        est = self.tracker.estimate
        if est is None:
            return WriteDecision(False, DecisionReason.NO_CALIBRATION, message="the tracker has no calibration yet")
        first = self._judge(est, device)
        return self._checked(device, first) if first.write else first

    def _checked(self, device: Calibration | None, first: WriteDecision) -> WriteDecision:
        """The last step before a write: the calibration as it may be reported
        (``tracker_check.checked``: a model fit's gates accept on the samples in memory, each σ
        at least fit's there) judged again. That costs a fit of memory (tens of ms), so it is
        made only when all else says write, and a refusal stands for ``RECHECK_SAMPLES``."""
        n = self.tracker.n
        if self._held is not None and n - self._held[0] < RECHECK_SAMPLES:
            return self._held[1]
        rep = checked(self.tracker)
        out = self._judge(rep, device) if rep is not None else WriteDecision(
            False, DecisionReason.GATE, first.calibration, first.comparison, first.gates,
            "fit's gates refuse every model on the samples in memory")
        self._held = None if out.write else (n, out)
        return out

    def _judge(self, est, device: Calibration | None) -> WriteDecision:
        """Gates, significance and budget for the estimate ``est``."""
        gates = tuple(self._gates(est))
        failing = [g for g in gates if not g.passed]
        if failing:
            return WriteDecision(False, DecisionReason.GATE, est.calibration, gates=gates,
                                 message="; ".join(g.message for g in failing))
        cmp = None if device is None else compare(self.tracker, device, est)
        if cmp is not None and not cmp.z >= self.z_needed:
            return WriteDecision(False, DecisionReason.NOT_SIGNIFICANT, est.calibration, cmp, gates,
                                 f"gain z = {cmp.z:.2f} < {self.z_needed:.2f}")
        if self.tokens < 1.0:
            wait_s = (1.0 - self.tokens) * DAY_S / self.budget.per_day
            return WriteDecision(False, DecisionReason.BUDGET, est.calibration, cmp, gates,
                                 f"EEPROM budget spent for now ({self.budget.per_day:g}/day); next write in {wait_s:.0f} s")
        reason = DecisionReason.FIRST if device is None else DecisionReason.BETTER
        msg = "the device holds no calibration" if cmp is None else (
            f"RMS {cmp.rms_other_pct:.3f} % → {cmp.rms_ours_pct:.3f} %, z = {cmp.z:.1f}")
        return WriteDecision(True, reason, est.calibration, cmp, gates, msg, est)

    def affords(self, now_s: float) -> bool:
        """Is a write within the budget now?"""
        self._refill(now_s)
        return self.tokens >= 1.0

    def spent(self, now_s: float, cycles: int, verified: bool) -> None:
        """A write was made (``cycles``: EEPROM writes it took, 2 when the old record was put back)."""
        self._refill(now_s)
        self.tokens -= cycles
        self.cycles += cycles
        if verified:
            self.writes += 1
        else:
            self.failed += 1

    def charge_history(self, spent_at_s, writes: int, failed: int) -> None:
        """The budget as the write ledger says it was spent (``app.daemon.ledger``): every EEPROM
        command one cycle at its time, the bucket full before the first. The ledger is made
        durable before each command, so it knows every write a state file saved earlier may have
        missed: the fewer tokens of the two stand, and its counts are the counts."""
        times = sorted(float(t) for t in spent_at_s)
        if not times:
            return
        rate = self.budget.per_day / DAY_S
        tokens, at = float(self.budget.burst), times[0]
        for t in times:
            tokens = min(float(self.budget.burst), tokens + max(t - at, 0.0) * rate) - 1.0
            at = t
        ref = max(at, self.refilled_s)
        self._refill(ref)
        self.tokens = min(self.tokens, min(float(self.budget.burst), tokens + (ref - at) * rate))
        self.cycles, self.writes, self.failed = len(times), int(writes), int(failed)

    def status(self) -> dict:
        return {"writes": self.writes, "failed": self.failed, "eeprom_cycles": self.cycles,
                "budget_per_day": self.budget.per_day, "burst": self.budget.burst,
                "tokens": round(self.tokens, 3), "z_needed": round(self.z_needed, 3),
                "estimate": None if self.tracker.estimate is None else self.tracker.estimate.to_dict()}

    def to_state(self) -> dict:
        return {"tracker": self.tracker.to_state(), "tokens": self.tokens, "refilled_s": self.refilled_s,
                "cycles": self.cycles, "writes": self.writes, "failed": self.failed}

    def load_state(self, d: dict) -> None:
        """Resume from ``to_state`` (ValueError when malformed); budget and gates stay this one's."""
        try:
            self.tracker = Tracker.from_state(d["tracker"])
            self._held = None
            self.tokens = min(float(d["tokens"]), float(self.budget.burst))
            self.refilled_s = float(d["refilled_s"])
            self.cycles, self.writes, self.failed = int(d["cycles"]), int(d["writes"]), int(d["failed"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"keeper state is malformed: {exc!r}") from None
        if not math.isfinite(self.tokens):
            raise ValueError("keeper state is malformed: tokens not finite")
