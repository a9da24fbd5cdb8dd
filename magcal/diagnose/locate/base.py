"""What every locator shares: the residual it searches, and what it says back.

A locator looks at one recording after its calibration and says *where* the data and the
model disagree — in time, in frequency, along a logged channel, on an axis — and, where it
can, *which physics* accounts for it. Each effect lives in one module of this package with an
``EFFECT`` value (its name, kind and search function); ``magcal.diagnose.locate.EFFECTS`` is
the one table the diagnosis loops over, so adding an effect touches one module and its test.

``Residual`` is the value every search reads; ``Located`` is what it returns. Sizes are
judged against the recording itself (``floor_ut``: the RMS radial residual of a plain
ellipsoid on the same samples, and ``noise_ut``: the white noise of one reading), never against
a floor the tool states for itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from functools import cached_property
from typing import Any, Callable, Mapping

import numpy as np

from ...core.calibration import Calibration
from ..channels import offset_wander
from ..limits import WANDER_BLOCKS

# the keys a ``where`` object may carry (issue: every finding and limit says where)
WHERE_KEYS = ("time_s", "channel", "lag_s", "frequency_hz", "axis", "direction")
AXES = ("x", "y", "z")
REST = "unexplained_structure"  # the effect name of structure located but named by no physics


class Kind(Enum):
    """What a located thing is."""

    PHYSICS = "physics"  # a named physical effect, with a model that can be fitted
    FAULT = "fault"  # a data fault: the samples it touches are set aside before the fit
    REMAINDER = "remainder"  # structure located but named by no physics (unexplained_structure)


@dataclass(frozen=True)
class Residual:
    """One recording seen through its calibration: what every locator searches.

    ``m_ut`` (n, 3) the samples as recorded (µT, sensor frame) and ``t_s`` their times, both in
    time order, glitches and faults already set aside; ``calibration`` the one returned;
    ``h_ut`` the corrected field, ``r_ut`` the radial residual |h| − field, ``u`` the unit
    directions of h; ``noise_ut`` the white noise of one reading per axis; ``floor_ut`` the RMS
    radial residual of a plain ellipsoid on these samples (the recording's own floor);
    ``channels`` the logged channels (no time), each (n,)."""

    t_s: np.ndarray
    m_ut: np.ndarray
    calibration: Calibration
    noise_ut: float
    floor_ut: float
    channels: Mapping[str, np.ndarray] = field(default_factory=dict)
    clock: bool = True  # False: t_s is the sample index (Series.clock), and seconds mean nothing

    # computed once and read-only: every locator reads them
    @cached_property
    def h_ut(self) -> np.ndarray:
        return _frozen(self.calibration.correct(self.m_ut, self._used_channels()))

    @cached_property
    def r_ut(self) -> np.ndarray:
        return _frozen(np.linalg.norm(self.h_ut, axis=1) - self.calibration.field_ut)

    @cached_property
    def u(self) -> np.ndarray:
        h = self.h_ut
        return _frozen(h / np.linalg.norm(h, axis=1, keepdims=True))

    def _used_channels(self) -> dict:
        used = getattr(self.calibration, "coef_ut_per_unit", None) or {}
        return {c: self.channels[c] for c in used if c in self.channels}

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass(frozen=True)
class Located:
    """One thing a locator found: a named effect, a data fault, or an honest remainder.

    ``effect`` names the physics (``hard_iron_step``, ``narrowband_line``, ``stuck_axis`` …, or
    ``unexplained_structure``); ``where`` holds only keys of ``WHERE_KEYS``; ``params`` the
    fitted values with units in their names; ``evidence`` how it was judged (sizes against the
    recording's floor, the statistic and its threshold, held-out gain); ``rows`` the positions
    (in the searched samples) a fault touches, to be set aside."""

    effect: str
    kind: Kind
    summary: str
    where: Mapping[str, Any] = field(default_factory=dict)
    params: Mapping[str, Any] = field(default_factory=dict)
    evidence: Mapping[str, Any] = field(default_factory=dict)
    rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False, compare=False)

    def __post_init__(self):
        unknown = set(self.where) - set(WHERE_KEYS)
        if unknown:
            raise ValueError(f"where has keys {sorted(unknown)}; allowed: {WHERE_KEYS}")

    def to_dict(self) -> dict:
        out = {
            "effect": self.effect,
            "kind": self.kind.value,
            "summary": self.summary,
            "where": _plain(dict(self.where)),
            "params": _plain(dict(self.params)),
            "evidence": _plain(dict(self.evidence)),
        }
        if len(self.rows):
            out["n_samples"] = int(len(self.rows))
        return out


@dataclass(frozen=True)
class Effect:
    """One row of the table the diagnosis loops over: the effect's name, its kind, its search
    (``Residual`` → found things, empty when nothing is there) and, for a modelled effect, its
    ``remove(m_ut, t_s, channels, located) → m_ut``: the samples with the effect taken out, so
    that the calibration refitted on them is the one in force at the end of the recording (or
    at the channel's reference value). ``simpler``, where the search tested the effect against a
    simpler account of the same change (a soft-iron change against the offset alone changing at
    its time), removes that account instead: held-out blocks must prefer the effect to it too.
    ``remove_trained(m_ut, t_s, channels, located, train)``, where the effect's parameters can be
    refitted, is ``remove`` with them fitted on the ``train`` samples alone, so a held-out block
    is scored by a change it did not help fit."""

    name: str
    kind: Kind
    search: Callable[[Residual], tuple[Located, ...]]
    remove: Callable[..., np.ndarray] | None = None
    simpler: Callable[..., np.ndarray] | None = None  # as ``remove``: the simpler account its search judged it against
    remove_trained: Callable[..., np.ndarray] | None = None  # as ``remove``, its parameters fitted on a training mask


def noise_and_wander_ut(r_ut: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    """What a radial residual shows with nothing more in it than the recording's own noise and
    slow wander, as (noise, wander) RMS per reading (µT): the white noise of one reading from the
    spread of successive differences (robust), and the offset wander as the ``offset_wander``
    limit measures it (offsets of ``WANDER_BLOCKS`` time blocks, their scatter beyond the noise).
    A remainder is judged against both, measured on the residual with that remainder taken out."""
    d = np.diff(np.asarray(r_ut, float))
    noise = float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0)) if len(d) else 0.0
    return noise, float(offset_wander(r_ut, u, WANDER_BLOCKS)[0])


def stretches(mask: np.ndarray, t_s: np.ndarray, min_len: int = 1) -> list[tuple[float, float]]:
    """The [start, end] times of each run of True in ``mask`` at least ``min_len`` long."""
    out = []
    for a, b in runs(mask, min_len):
        out.append((float(t_s[a]), float(t_s[b - 1])))
    return out


def runs(mask: np.ndarray, min_len: int = 1) -> list[tuple[int, int]]:
    """(start, stop) index pairs of each run of True in ``mask`` at least ``min_len`` long."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2]) if b - a >= min_len]


def repeats(m: np.ndarray) -> np.ndarray:
    """Reads equal to the one before on every axis, bit for bit: one conversion read again by a
    host polling faster than its sensor converts (the first read is never a repeat)."""
    return np.concatenate([[False], np.all(np.diff(m, axis=0) == 0, axis=1)])


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _plain(v):
    """JSON-ready: numpy scalars and arrays as Python numbers and lists."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, Enum):
        return v.value
    return v
