"""What a recording could not test, and whether it is suspected: the ``limits`` of a diagnosis.

Silence about a term must not read as "it is not there". ``Limit`` is one such statement, as a
value; each function below returns a tuple of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from . import channels, softiron, timewords


@dataclass(frozen=True)
class Limit:
    """What a recording could not test or pin down, and whether it is suspected there.

    ``to_dict`` is its JSON shape (``magcal.diagnose/1``): ``effect``, ``suspected``, then the
    ``channel`` it concerns, why the screen left that channel out (magcal.diagnose.hygiene), its
    own ``details`` (figures, in the order given) and its ``summary``; a limit located in the
    recording (``where``: magcal.diagnose.locate's remainder) states its summary and where first."""

    effect: str
    suspected: bool
    summary: str
    channel: str | None = None  # the logged channel (or time) it concerns
    left_out_because: str | None = None  # the screen left ``channel`` out of the candidates, for this reason
    details: Mapping[str, Any] = field(default_factory=dict)
    where: Mapping[str, Any] | None = None  # where in the recording it was located

    @property
    def left_out(self) -> bool:
        return self.left_out_because is not None

    def to_dict(self) -> dict:
        head = {"effect": self.effect, "suspected": self.suspected}
        if self.where is not None:
            return {**head, "summary": self.summary, "where": dict(self.where), **self.details}
        if self.channel is not None:
            head["channel"] = self.channel
        if self.left_out:
            head.update(left_out=True, reason=self.left_out_because)
        return {**head, **self.details, "summary": self.summary}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Limit:
        """The limit whose ``to_dict`` is ``d`` (key order included); ValueError naming what
        is missing or out of place otherwise."""
        missing = [k for k in ("effect", "suspected", "summary") if k not in d]
        if missing:
            raise ValueError(f"a limit needs {', '.join(missing)}; got the keys {', '.join(d) or 'none'}")
        rest = {k: v for k, v in d.items() if k not in ("effect", "suspected", "summary", "where", "channel",
                                                         "left_out", "reason")}
        because = d.get("reason") if d.get("left_out") else None
        limit = cls(d["effect"], bool(d["suspected"]), d["summary"], d.get("channel"), because, rest, d.get("where"))
        if list(limit.to_dict()) != list(d):
            raise ValueError(f"a limit's keys are out of their order or unknown: {', '.join(d)}")
        return limit


def untested_channels(tests: dict, by_effect: dict) -> tuple[Limit, ...]:
    """A channel term (``by_effect``: the channel candidates by group) the recording could not
    test at all is named, with why: silence about a column the user logged must not read as "it
    has no effect"."""
    out = []
    for g, c in by_effect.items():
        r = tests[g]
        if not (r.f == 0.0 and r.p >= 1.0):
            continue
        what = "time" if c.channel == channels.TIME else c.channel
        if c.confounded:
            what += " (with " + ", ".join(n for n, _ in c.confounded) + ", which only rose or fell with it)"
        if r.basis.shape[1] == 0:
            why = (
                "with this motion an offset that follows it looks the same as the hard iron, a "
                "direction-dependent error or the slow wander (the sensor pointed in different "
                "directions while it changed); record while it goes up and down with the board "
                "turning through all orientations"
            )
        else:
            why = "it varies in too few independent stretches of the recording to be tested against the slow wander"
        out.append(Limit(g, False, f"An offset following {what} could not be tested: {why}.", c.channel))
    return tuple(out)


WANDER_BLOCKS = 20


def by_direction(r) -> str:
    if not r:
        return ""
    lo, hi = r
    return f" ({lo:.2g}–{hi:.2g} by its direction)" if hi is not None else f" ({lo:.2g} or more by its direction; along some, not at all)"


def _searched(chans: dict, located: tuple = ()) -> str:
    """What was searched before a wander is left unexplained (magcal.diagnose.locate); with
    ``located``, the names of what was found elsewhere in the recording."""
    logged = sorted(c for c in chans if c != channels.TIME)
    lead = ("beside what was located (" + ", ".join(sorted(set(located))) + "), nothing more" if located
            else "no step, narrowband line or data fault") + " was located to account for it"
    if not logged:
        return lead + ", and no channel is logged that could (a temperature, a current)"
    return lead + (f", and {', '.join(logged)} did not, each tried as an offset, with a lag, as a gain and in "
                   "nonlinear forms")


def wander_limit(wander, chans: dict, alpha: float, floor_ut: float, untested: list, clock: bool = True,
                 located: tuple = ()) -> tuple[Limit, ...]:
    """Real recordings wander: the offset moves slowly in a way no logged channel explains.
    That is not a calibration term (it cannot be predicted for the next session), but it bounds
    what the calibration is good for and what slow effects this recording can identify, so it
    is stated when the full model's block offsets (``wander``, statements.BlockWander) scatter beyond
    the noise (χ², at ``alpha``) by more than the practical floor."""
    rms, p, u = wander.rms_ut, wander.p_value, wander.directions
    if not (p < alpha and rms >= floor_ut):
        return ()
    others = [c for c in untested if c != channels.TIME]
    if others:
        tail = f"; an effect of {', '.join(others)} or of time that varies this slowly could not be told apart from it"
    elif any(c != channels.TIME for c in chans):  # every logged channel is in the model
        tail = "; a drift in time that varies this slowly could not be told apart from it"
    else:
        tail = "; a temperature (none is logged) or drift effect that varies this slowly could not be told apart from it"
    # how large a slow term of each channel not in the model would have had to be
    floors, ranges = {}, {}
    for c in untested:
        f = channels.slow_term_floor(chans[c], rms, channels.WANDER_RATIO, WANDER_BLOCKS) if c in chans else None
        if f is not None:
            floors[c] = f
            ranges[c] = channels.slow_term_floor_range(chans[c], u, rms, channels.WANDER_RATIO, WANDER_BLOCKS)
    if floors:
        tail += " (to be reported, a slowly varying term would have needed about " + ", ".join(
            f"{v:.2g} µT/{channels.unit_of(c, clock)} of {'drift in time' if c == channels.TIME else c}"
            + by_direction(ranges.get(c))
            for c, v in floors.items()
        ) + ")"
    p_text = "p < 1e-12" if p < 1e-12 else f"p = {p:.1g}"
    summary = (
        f"The offset wanders slowly by about {rms:.2f} µT RMS between {WANDER_BLOCKS} stretches of the recording, "
        f"more than the noise allows ({p_text}){_concentrated(wander)}; {_searched(chans, located)}: a calibration from "
        f"this recording is good to about that much{tail}."
    )
    details = {
        "rms_ut": rms,
        "p_value": p,
        "blocks": WANDER_BLOCKS,
        "slow_term_floor_ut_per_unit": floors,
        "slow_term_floor_range_ut_per_unit": {c: list(r) for c, r in ranges.items() if r},
    }
    if wander.stretches_s:
        details["concentrated_share"] = wander.stretch_share
    where = {"time_s": [list(s) for s in wander.stretches_s]} if wander.stretches_s else None
    return (Limit("offset_wander", True, summary, details=details, where=where),)


def _concentrated(wander) -> str:
    """Where in time the wander sits, when a few stretches or one jump carry it."""
    if wander.jump is not None:
        return f", most of it ({100 * wander.jump.share:.0f} %) one jump at about {timewords.instant(wander.jump.time_s)}"
    if not wander.stretches_s:
        return ""
    at = [timewords.stretch(a, b) for a, b in wander.stretches_s]
    at = at[0] if len(at) == 1 else ", ".join(at[:-1]) + " and " + at[-1]
    return f", most of it at {at} ({100 * wander.stretch_share:.0f} % of it there)"


# the final model's residual this much above what it predicts for the measured noise is
# practically "something left unmodelled" (simulated clean recordings stay within ±7 %)
SUSPECT_EXCESS = 1.15


def _soft_iron_reasons(k: int, determined: int, accepted: bool, untested: bool, duration_s: float) -> list:
    reasons = []
    if k < 5:
        text = (f"with this motion only {k} of the 5 soft-iron directions can be told apart from the offset, the "
                "radius and a slow wander in time")
        if accepted and determined > k:
            text += (f"; soft iron is fitted along the {determined} the motion determines, but along {determined - k} "
                     "of them the fit may hold slow wander as much as soft iron")
        if determined < 5:
            text += f"; along {5 - determined} it cannot be fitted at all, so a scale mismatch there would go unseen"
        reasons.append(text + "; turn the board through all orientations, visiting each more than once")
    if untested and k > 0:
        reasons.append(
            f"the {timewords.duration(duration_s, '.0f')} of motion hold too few independent stretches to test it against slow "
            "wander; record longer (a few minutes), turning through all orientations more than once"
        )
    return reasons


def soft_iron_limits(test, accepted: bool, determined: int, rms_ut: float, simulated_rms_ut: float,
                     duration_s: float) -> tuple[Limit, ...]:
    """Say so when the recording could not test soft iron fully — too few directions covered,
    or too few independent stretches of motion — and whether the residual suggests it is
    there: silence must not read as "no soft iron". ``determined``: how many of the five
    directions the motion determines (and the model carries when soft iron is found)."""
    k = int(test.basis.shape[1])
    untested = test.p >= 1.0 and test.f == 0.0
    if k >= 5 and not untested:
        return ()
    reasons = _soft_iron_reasons(k, determined, accepted, untested, duration_s)
    excess = rms_ut / simulated_rms_ut if simulated_rms_ut > 0 else float("nan")
    suspected = bool(np.isfinite(excess) and excess >= SUSPECT_EXCESS)
    part = "along the directions it could test, soft iron is modelled; beyond them it " if accepted else "Soft iron "
    lead = (
        part[0].upper() + part[1:] + f"is suspected but not identifiable: the residual ({rms_ut:.2f} µT) is "
        f"{excess:.2f}× what the fitted model predicts for this noise, and "
        if suspected
        else "Soft iron could not be fully tested: "
    )
    details = {
        "identifiable_directions": k,
        "determined_directions": int(determined),
        "of_directions": 5,
        "residual_over_predicted": float(excess),
    }
    return (Limit(softiron.EFFECT, suspected, lead + "; ".join(reasons) + ".", details=details),)
