"""Locate what the catalogue does not know: data faults, steps, lines, lagged channels.

``EFFECTS`` is the one table of located effects; each row comes from the module that owns the
effect (``magcal.diagnose.locate.base.Effect``). The diagnosis screens data faults before the
fit, runs every other row on the calibrated residual (``step.locate_and_model``), keeps a named
effect only where it improves time-blocked held-out prediction (``judge``), and states what it
found here: ``as_findings`` (data faults, and named effects that earned their place) and
``as_limits`` (what was located but not modelled, and the honest remainder).
"""

from __future__ import annotations

from dataclasses import replace

from ..finding import Finding
from ..limits import Limit
from . import channel_forms, faults, lines, steps
from .base import AXES, REST, WHERE_KEYS, Effect, Kind, Located, Residual, runs, stretches

EFFECTS: tuple[Effect, ...] = (*faults.EFFECTS, *steps.EFFECTS, lines.EFFECT, *channel_forms.EFFECTS)


def as_findings(found: tuple[Located, ...], verdicts: tuple) -> tuple[Finding, ...]:
    """Data faults, and each named effect kept on held-out blocks, as findings."""
    faults = tuple(_finding(x, {}) for x in found if x.kind is Kind.FAULT)
    kept = tuple(_finding(v.located, v.evidence()) for v in verdicts if v.kept)
    return faults + kept


def one_per_channel(catalogue: tuple[Finding, ...], located: tuple[Finding, ...]) -> tuple[Finding, ...]:
    """The catalogue's findings then the located ones, one finding per channel: a located term
    kept on a channel the catalogue also found (its lag, gain or curve fitted to the channel's
    whole effect, ``step.replacing``) stands in place of the catalogue's no-lag term, which it
    names in its evidence (``replaces``)."""
    on = {f.where.get("channel"): f for f in located if f.where.get("channel")}
    out, gone = [], {}
    for f in catalogue:
        if f.where.get("channel") in on:
            gone[f.where["channel"]] = f
        else:
            out.append(f)
    return tuple(out) + tuple(_in_place_of(f, gone.get(f.where.get("channel"))) for f in located)


def _in_place_of(f: Finding, old: Finding | None) -> Finding:
    if old is None:
        return f
    was = {"effect": old.effect, "coef_ut_per_unit": old.params.get("coef_ut_per_unit"), "summary": old.summary}
    note = f" It stands in place of the no-lag {old.effect.replace('_', ' ')} the channel test found."
    return replace(f, summary=f.summary + note, evidence={**f.evidence, "replaces": was})


def as_limits(found: tuple[Located, ...], verdicts: tuple = ()) -> tuple[Limit, ...]:
    """The honest remainder (``unexplained_structure``), with its ``where``: what was located
    but named by no physics, and what was located and resembles a named effect but did not
    improve unseen blocks when modelled — that is no finding, and is not named as one."""
    judged = {id(v.located): v for v in verdicts}
    modelled = {v.located.params.get("channel") for v in verdicts if v.kept} - {None}
    out = []  # one the held-out blocks contradict (worse with it modelled), whose held-out gain is within the noise and
    # slow wander the recording keeps without it (the offset_wander limit states that), or whose gain one or two blocks
    # carry (judge.Verdict.spread: the median block's is within them), stays in the JSON's located only
    for x in found:
        v = judged.get(id(x))
        if x.kind is Kind.REMAINDER:
            if x.where.get("channel") not in modelled:  # a kept term on the channel accounts for its structure
                out.append(_remainder(x, x.summary, {}))
        elif x.kind is Kind.PHYSICS and not (v and (v.kept or v.contradicted or v.within_noise_and_wander or not v.spread)):
            why = v.reason if v is not None else "no held-out verdict"
            out.append(_remainder(x, f"Structure located that resembles a {x.effect.replace('_', ' ')}, not claimed as "
                                     f"one because modelling it did not earn its place ({why}): {x.summary}",
                                  {"resembles": x.effect}))
    return tuple(out)


def said(found: tuple[Located, ...], verdicts: tuple = ()) -> tuple[str, ...]:
    """The effects of what was located that the diagnosis states, as a finding or as the
    remainder (what it resembles). A located effect the held-out blocks set aside — worse with
    it, or within the noise and slow wander — is stated nowhere but the JSON's ``located``: it is
    part of the offset's wander, not something beside it."""
    return (tuple(f.effect for f in as_findings(found, verdicts))
            + tuple(x.details.get("resembles", x.effect) for x in as_limits(found, verdicts)))


def _remainder(x: Located, summary: str, extra: dict) -> Limit:
    d = x.to_dict()
    return Limit(REST, True, summary, details={"params": d["params"], **extra}, where=d["where"])


def _finding(x: Located, extra: dict) -> Finding:
    d = x.to_dict()
    held = f". Modelled: {extra['why']}." if extra.get("why") else ""
    return Finding(x.effect, x.summary.rstrip(".") + held if held else x.summary, d["where"], {**d["evidence"], **extra, "kind": x.kind.value}, d["params"])


__all__ = ["AXES", "WHERE_KEYS", "EFFECTS", "Effect", "Kind", "Located", "Residual", "as_findings", "as_limits",
           "one_per_channel", "runs", "stretches"]
