"""Two candidates that share their columns: soft iron and an offset drifting in time.

Every candidate is tested beside every other, so that a drift is not credited to soft iron nor
soft iron to a drift. On a band of directions swept with a period, though, soft iron and a
straight-line offset in time look much alike (the direction follows time), and each tested
beside the other keeps little of its power: a simulated 1.1 % soft iron on a ±17° band was
significant at p 5e-6 without the time columns and at p 0.08 beside them, time at p 0.02
beside soft iron — neither passed Holm's step, though the pair is plainly there.

The rule (``resolve``): when neither member passes Holm's step beside the other, the two are
tested together as one group. That joint test is one more hypothesis of Holm's family (a third
look at the pair's two hypotheses), and the member that alone — each tested without the other's
columns — explains more (the smaller p of its own test) is tested that way, with a p never below
the joint test's; the other stays tested beside it. So the chosen member passes only where the
pair does, at a family one test larger, and it still has to pass the practical floor, the
wander gate and the held-out comparison as any other term. A drift alone on a band explains
more as time than as soft iron, and soft iron alone more as soft iron; where the two explain
nearly alike the choice can go wrong, which is why the pair must first pass as a pair. The
decision is a ``PairChoice``, carried in the JSON's evidence of the member it credits.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from . import channels, softiron
from .inference import WaldResult, block_wald, calibrated

PAIR = (softiron.EFFECT, channels.effect_name(channels.TIME))


@dataclass(frozen=True)
class Tested:
    """What every test of the design ran on: its columns (with or without the wander
    nuisance), the residual, the named groups, each group's coverage gate and the twin's draws."""

    x: np.ndarray
    residual_ut: np.ndarray
    groups: dict
    unique: dict
    null: tuple | None

    def test(self, groups: dict, without: np.ndarray = np.zeros(0, int)) -> dict:
        """Each of ``groups`` (name → column indices of x) tested beside every column of x but
        ``without``, judged against the twin's draws as the other tests are; a group the
        coverage gates do not name has the strictest of them (soft iron's)."""
        keep = np.setdiff1d(np.arange(self.x.shape[1]), without)
        cols = {g: np.searchsorted(keep, c) for g, c in groups.items()}
        unique = {g: self.unique.get(g, max(self.unique.values())) for g in groups}
        results = block_wald(self.x[:, keep], self.residual_ut, cols, min_unique=unique, null=self.null)
        return {g: calibrated(r) for g, r in results.items()}


@dataclass(frozen=True)
class PairChoice:
    """The decision about the pair: tested jointly only when neither member passed beside the
    other; ``chosen`` the member then tested without the other ("" when none was)."""

    members: tuple  # (soft iron, time)
    beside_p: tuple  # each member's p beside the other (as in Holm's family before the choice)
    joint_f: float = float("nan")
    joint_df: tuple = (0, 0)
    joint_p: float = 1.0
    alone_p: tuple = (1.0, 1.0)  # each member's p without the other's columns
    chosen: str = ""
    reason: str = ""

    def family_entry(self) -> dict:
        """The joint test as one more hypothesis of Holm's family, when a member was chosen
        (the chosen member's p is never below it): a third look at the pair's two hypotheses."""
        return {("pair", "+".join(self.members)): self.joint_p} if self.chosen else {}

    def to_dict(self) -> dict:
        return {"members": list(self.members), "p_beside_each_other": list(self.beside_p),
                "joint_F": self.joint_f, "joint_df": list(self.joint_df), "joint_p": self.joint_p,
                "p_alone": list(self.alone_p), "chosen": self.chosen or None, "reason": self.reason}


def _testable(tests: dict, g: str) -> bool:
    return g in tests and not tests[g].untestable


def resolve(tested: Tested, tests: dict, rejected: dict, alpha: float) -> tuple[dict, PairChoice | None]:
    """The tests with the pair's decision applied (see the module docstring), and the decision
    (None when the design does not hold both members or either cannot be tested)."""
    a, b = PAIR
    if not (_testable(tests, a) and _testable(tests, b)):
        return tests, None
    beside = (tests[a].p, tests[b].p)
    if rejected.get(a, False) or rejected.get(b, False):
        return tests, PairChoice(PAIR, beside, reason="a member passed beside the other")
    ca, cb = tested.groups[a], tested.groups[b]
    joint: WaldResult = tested.test({"pair": np.concatenate([ca, cb])})["pair"]
    common = dict(members=PAIR, beside_p=beside, joint_f=joint.f, joint_df=(joint.df1, joint.df2), joint_p=joint.p)
    if joint.p > alpha:
        return tests, PairChoice(**common, reason="the pair tested together is not significant either")
    alone = {a: tested.test({a: ca}, without=cb)[a], b: tested.test({b: cb}, without=ca)[b]}
    chosen = min(PAIR, key=lambda g: alone[g].p)
    other = b if chosen == a else a
    reason = (f"neither passed beside the other but the pair together did (p = {joint.p:.2g}); alone, {chosen} "
              f"explains more (p = {alone[chosen].p:.2g} against {alone[other].p:.2g} for {other}), so it is "
              f"tested without {other}'s columns")
    return ({**tests, chosen: replace(alone[chosen], p=max(alone[chosen].p, joint.p))},
            PairChoice(**common, alone_p=(alone[a].p, alone[b].p), chosen=chosen, reason=reason))
