"""The AK8975 self-test result: what the internal coil read, judged against the datasheet window.

Every backend that can run the self-test (``i2c:`` on the chip directly, the firmware's ``T``
command over serial, the simulated board) returns this value; the judgement lives here once.
"""

from __future__ import annotations

from dataclasses import dataclass

from .sample import ST2_DERR, ST2_HOFL, asa_gain

# Self-test pass window in ASA-adjusted counts (datasheet MS1187-E-02, self-test judgement).
SELF_TEST_WINDOW = ((-100, 100), (-100, 100), (-1000, -300))


@dataclass(frozen=True)
class SelfTestResult:
    """The AK8975 self-test: the internal field's reading per axis against the pass window."""

    raw: tuple[int, int, int]
    adjusted: tuple[float, float, float]  # raw · (ASA+128)/256, what the window applies to
    window: tuple[tuple[int, int], ...] = SELF_TEST_WINDOW
    st2: int = 0

    @classmethod
    def from_registers(cls, raw, asa, st2: int = 0, window=SELF_TEST_WINDOW) -> "SelfTestResult":
        """The data registers read in self-test mode and this chip's ASA bytes, judged against
        ``window`` (the chip's own: ``magcal.core.chips.Chip.self_test_window``; default the AK8975's)."""
        raw = tuple(int(v) for v in raw)
        adjusted = tuple(float(r) * asa_gain(a) for r, a in zip(raw, asa))
        return cls(raw=raw, adjusted=adjusted, window=tuple(tuple(w) for w in window), st2=int(st2))

    @property
    def axis_passed(self) -> tuple[bool, bool, bool]:
        ok = tuple(lo <= v <= hi for v, (lo, hi) in zip(self.adjusted, self.window))
        if self.st2 & (ST2_DERR | ST2_HOFL):
            return (False, False, False)
        return ok  # type: ignore[return-value]

    @property
    def passed(self) -> bool:
        return all(self.axis_passed)

    def to_dict(self) -> dict:
        return {
            "passed": self.passed,
            "axes": {
                name: {"raw": r, "adjusted": round(a, 2), "window": list(w), "passed": p}
                for name, r, a, w, p in zip("xyz", self.raw, self.adjusted, self.window, self.axis_passed)
            },
            "st2": self.st2,
        }
