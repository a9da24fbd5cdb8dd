"""FitFailure: the value a fit returns instead of a model when the data cannot support one.

It is falsy, so ``if not fit: ...`` works, and it carries a short machine-readable ``reason``
code plus a sentence for people. Asking it for anything a model has (``offset_ut``,
``calibration`` …) raises an AttributeError that says the fit failed and why, instead of the
bare "no attribute" of a value used without its check. Reason codes used across ``magcal.fit``:

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

    def __getattr__(self, name: str):
        """Only for names the value does not have (its fields and methods are found first)."""
        if name.startswith("__"):  # copy, pickle and friends probe for optional hooks
            raise AttributeError(name)
        why = f"{self.__dict__.get('reason')}: {self.__dict__.get('message')}"  # never this method again
        raise AttributeError(f"{name!r}: the fit failed ({why}), so there is no "
                             f"{name!r}; a FitFailure has only reason and message — test the result "
                             "(`if not fit:`) before using it")

    def to_dict(self) -> dict:
        return {"failure": self.reason, "message": self.message}

    def __str__(self) -> str:
        return f"{self.reason}: {self.message}"
