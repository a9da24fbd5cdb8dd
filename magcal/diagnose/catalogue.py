"""What a catalogue effect is: one value per term the diagnosis fits, and what it is built from.

Each effect the diagnosis tests or carries as a nuisance — soft iron (magcal.diagnose.softiron),
one offset-versus-channel term per channel (magcal.diagnose.channels), the direction harmonics
(magcal.diagnose.harmonics), the slow offset wander (magcal.diagnose.wander) — is one
``CatalogueEffect`` held in its own module as ``TERM``: its name, its role in the tests, how its
columns are made from the shared linearisation (``Linearised``), how an accepted term of it is
described, and how its identifiability is judged. ``magcal.diagnose.design.CATALOGUE`` lists
them in order, and ``design.build`` loops over that table, so adding an effect is one module
with its ``TERM`` and one entry in the table. (The effects the locate step finds in the
residual after the calibration have their own table: magcal.diagnose.locate.EFFECTS.)
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Callable, Mapping

import numpy as np

from .finding import Finding
from .model import ModelFit


class Role(Enum):
    """What an effect's columns are to the tests of the design."""

    ABSORBED = "absorbed"  # what any refit takes up anyway (offset and radius): leading columns, never tested
    TESTED = "tested"  # each named group tested for being zero (design.Design.groups)
    NUISANCE = "nuisance"  # beside every test (the direction harmonics)
    WANDER = "wander"  # beside the tests only where the residual shows a wander: trailing columns


@dataclass(frozen=True)
class Linearised:
    """The shared point every effect's columns are made at (design.linearise): the samples
    ``m_ut`` (n, 3), times ``t_s`` and channels ``chans`` (time included); the ``reference``
    model and the channel ``candidates`` with their coefficients ``coefs`` (µT per unit, in
    candidate order, concatenated) where the design is linearised; the radial residual there
    ``residual_ut`` and its Jacobian ``jac`` over (offset, the five soft-iron coordinates,
    radius, three per candidate channel), its soft-iron columns taken at the model's own point
    on the surface; the calibrated unit field ``directions`` (n, 3) and ``offset_directions``
    W·u (how an offset change shows in the residual)."""

    m_ut: np.ndarray
    t_s: np.ndarray
    chans: Mapping[str, np.ndarray]
    reference: ModelFit
    candidates: tuple
    coefs: np.ndarray
    residual_ut: np.ndarray
    jac: np.ndarray
    directions: np.ndarray
    offset_directions: np.ndarray

    @property
    def jac_offset(self) -> np.ndarray:
        return self.jac[:, 0:3]

    @property
    def jac_soft(self) -> np.ndarray:
        return self.jac[:, 3:8]

    @property
    def jac_radius(self) -> np.ndarray:
        return self.jac[:, 8:9]

    @property
    def jac_channels(self) -> np.ndarray:
        return self.jac[:, 9:]


@dataclass(frozen=True)
class Columns:
    """What one effect adds to the design at a linearisation: its columns ``x`` (n, k) in
    order; the (name, width) of each group of them that is tested, in column order (none for a
    nuisance); ``at_reference`` (n,), its first-order share of the residual at the reference,
    taken back out so that its test is of the term being zero where the model fits;
    ``rest`` (n, r), its columns along the directions its tests leave out (fitted beside every
    candidate, never tested); ``parameter_dirs`` (p, k), the combinations of its p parameters
    its tested columns stand for, where they are not simply its parameters."""

    x: np.ndarray
    groups: tuple[tuple[str, int], ...] = ()
    at_reference: np.ndarray | None = None
    rest: np.ndarray | None = None
    parameter_dirs: np.ndarray | None = None

    def __post_init__(self):
        if self.x.ndim != 2:
            raise ValueError(f"an effect's columns are (samples, columns); got the shape {self.x.shape}")
        width = sum(w for _, w in self.groups)
        if width > self.x.shape[1]:
            raise ValueError(f"the tested groups {[g for g, _ in self.groups]} take {width} columns of {self.x.shape[1]}")


@dataclass(frozen=True)
class Accepted:
    """What an accepted term is described from (statements.findings): its ``group``, the
    refitted model ``final``, the statistics behind it (``evidence``), the analysed samples'
    channels (time included) and times, whether the recording has a clock, the design's
    channel candidates by group, and ``uncertainty``: a coefficient (µT per unit) → the
    entries that state its interval."""

    group: str
    final: ModelFit
    evidence: Mapping
    chans: Mapping[str, np.ndarray]
    t_s: np.ndarray
    clock: bool
    candidates: Mapping
    uncertainty: Callable[[np.ndarray], dict]


@dataclass(frozen=True)
class CatalogueEffect:
    """One row of the table ``design.build`` loops over.

    ``name`` the effect's name (a tested effect's groups carry their own names: soft iron's is
    its own, a channel's says the physics, ``temperature_drift``, ``current_interference`` …);
    ``role`` what its columns are to the tests; ``columns`` how they are made from the shared
    linearisation; ``describe`` an accepted term of it as a ``Finding`` (a tested effect);
    ``min_unique`` how its identifiability is judged: a tested direction whose column keeps less
    than this share of its length once every other column is fitted is left out of the test
    (inference.block_wald's coverage gate)."""

    name: str
    role: Role
    columns: Callable[[Linearised], Columns]
    describe: Callable[[Accepted], Finding] | None = None
    min_unique: float | None = None

    def __post_init__(self):
        if self.role is Role.TESTED and (self.describe is None or self.min_unique is None):
            raise ValueError(f"the tested effect {self.name!r} needs a describe and a min_unique")
