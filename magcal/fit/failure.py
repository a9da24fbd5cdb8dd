"""FitFailure: the value a fit returns instead of a model when the data cannot support one.

It is falsy, so ``if not fit: ...`` works, and it carries a short machine-readable ``reason``
code plus a sentence for people. Reason codes used across ``magcal.fit``:

``too_few_samples``, ``ill_conditioned`` (coverage too thin for the parameters asked for),
``degenerate`` (the data describe no sphere/ellipsoid, e.g. a negative squared radius),
``non_finite`` (NaN/inf in the input), ``no_convergence``, ``not_positive_definite``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FitFailure:
    reason: str
    message: str

    def __bool__(self) -> bool:
        return False

    def to_dict(self) -> dict:
        return {"failure": self.reason, "message": self.message}

    def __str__(self) -> str:
        return f"{self.reason}: {self.message}"
