"""Locate what the catalogue does not know: data faults, steps, lines, lagged channels.

``EFFECTS`` is the one table of located effects; each row comes from the module that owns the
effect (``magcal.diagnose.locate.base.Effect``). The diagnosis screens data faults before the
fit, runs every other row on the calibrated residual (``step.locate_and_model``), keeps a named
effect only where it improves time-blocked held-out prediction (``judge``), and states what it
found here: ``as_findings`` (data faults, and named effects that earned their place) and
``as_limits`` (what was located but not modelled, and the honest remainder).
"""

from __future__ import annotations

from ..finding import Finding
from . import lines
from .base import AXES, WHERE_KEYS, Effect, Kind, Located, Residual, runs, stretches

EFFECTS: tuple[Effect, ...] = (lines.EFFECT,)


def as_findings(found: tuple[Located, ...], verdicts: tuple) -> tuple[Finding, ...]:
    """Data faults, and each named effect kept on held-out blocks, as findings."""
    faults = tuple(_finding(x, {}) for x in found if x.kind is Kind.FAULT)
    kept = tuple(_finding(v.located, v.evidence()) for v in verdicts if v.kept)
    return faults + kept


def as_limits(found: tuple[Located, ...], verdicts: tuple = ()) -> tuple[dict, ...]:
    """What was located but not modelled (named, yet no better on unseen blocks), and the
    honest remainder (``unexplained_structure``), as limits with their ``where``."""
    judged = {id(v.located): v for v in verdicts}
    out = []
    for x in found:
        v = judged.get(id(x))
        if x.kind is Kind.REMAINDER or (x.kind is Kind.PHYSICS and not (v and v.kept)):
            why = f"; not modelled: {v.reason}" if v is not None else ""
            out.append({"effect": x.effect, "suspected": True, "summary": x.summary + why, "where": dict(x.where),
                        "params": x.to_dict()["params"]})
    return tuple(out)


def _finding(x: Located, extra: dict) -> Finding:
    d = x.to_dict()
    held = f" Modelled: {extra['why']}." if extra.get("why") else ""
    return Finding(x.effect, x.summary + held, d["where"], {**d["evidence"], **extra, "kind": x.kind.value}, d["params"])


__all__ = ["AXES", "WHERE_KEYS", "EFFECTS", "Effect", "Kind", "Located", "Residual", "as_findings", "as_limits",
           "runs", "stretches"]
