"""Why a calibration did not end on the device, verified: one vocabulary for ``calibrate``,
``write`` and the daemon (``run``).

A ``Failure`` is a ``Reason`` and, when a gate refused the fit, the gate's name: the session's
``failure``, a write's ``WriteResult.failure`` and the daemon's journal all hold one. The exit
status of a command is looked up from its reason (``magcal.cli.exits.exit_for``), never read
from its text. In JSON it is ``"failure": <reason>`` and ``"failed_gate": <name or null>``.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.events import Code


class Reason(Code):
    TIMEOUT = "timeout"  # collecting: the time was up before every gate passed
    END_OF_DATA = "end_of_data"  # collecting: the source ended before every gate passed
    FIT_FAILED = "fit_failed"  # the data support no model (the fit's FitFailure says why)
    GATE = "gate"  # the final fit fails a gate (``Failure.gate`` names the first)
    WRITE_FAILED = "write_failed"  # refused, no reply, port lost
    VERIFY_MISMATCH = "verify_mismatch"  # the echo or the read-back differs
    VERIFY_FAILED = "verify_failed"  # written, but it could not be read back


@dataclass(frozen=True)
class Failure:
    reason: Reason
    gate: str | None = None  # the failing gate, for Reason.GATE only

    def __post_init__(self):
        if not isinstance(self.reason, Reason):
            raise TypeError(f"a failure's reason is a Reason, not {self.reason!r}")
        if (self.reason is Reason.GATE) != (self.gate is not None):
            raise ValueError(f"a gate failure names its gate and only it does: {self.reason}, gate={self.gate!r}")

    @classmethod
    def of_gate(cls, name: str) -> "Failure":
        return cls(Reason.GATE, name)

    def to_dict(self) -> dict:
        return {"failure": self.reason.value, "failed_gate": self.gate}

    def __str__(self) -> str:
        return f"{self.reason} ({self.gate})" if self.gate else str(self.reason)


TIMEOUT = Failure(Reason.TIMEOUT)
END_OF_DATA = Failure(Reason.END_OF_DATA)
FIT_FAILED = Failure(Reason.FIT_FAILED)
WRITE_FAILED = Failure(Reason.WRITE_FAILED)
VERIFY_MISMATCH = Failure(Reason.VERIFY_MISMATCH)
VERIFY_FAILED = Failure(Reason.VERIFY_FAILED)


def fields(failure: Failure | None) -> dict:
    """``failure`` and ``failed_gate`` for a report, both None when nothing failed."""
    return failure.to_dict() if failure is not None else {"failure": None, "failed_gate": None}
