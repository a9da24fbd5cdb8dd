"""The candidate design: every term diagnosis may add, as columns of one linear regression.

At the baseline (hard iron + radius) the radial residual e is regressed on the columns of each
effect of ``CATALOGUE``, in its order (each a magcal.diagnose.catalogue.CatalogueEffect held in
its own module):

* the baseline's own Jacobian (offset and radius: what the refit would absorb anyway, ``BASELINE``);
* soft iron, the five degree-2 directions (magcal.diagnose.softiron);
* one offset-versus-channel term per candidate channel, three columns each (magcal.diagnose.channels);
* nuisance columns: the degree-3/4 direction harmonics (magcal.diagnose.harmonics) and a slow
  offset wander in time (magcal.diagnose.wander).

Each named group of columns is then tested for being zero by the block-HAC Wald test of
magcal.diagnose.inference, and a channel group a second time against a rich wander.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..core.calibration import Calibration
from . import channels, harmonics, softiron, wander
from .catalogue import CatalogueEffect, Columns, Linearised, Role
from .inference import block_wald, calibrated
from .model import ModelFit, Spec, residual_jacobian

# the slow wander as a nuisance (magcal.diagnose.wander.NUISANCE_DEGREE), named here for its readers
WANDER_DEGREE = wander.NUISANCE_DEGREE
# the second test of each channel: against a wander up to this degree, on at most RICH_MAX rows
RICH_DEGREE = 12
RICH_MAX = 50_000


def _offset_and_radius(lin: Linearised) -> Columns:
    return Columns(np.concatenate([lin.jac_offset, lin.jac_radius], axis=1))


# the baseline's own columns, which any refit absorbs: the leading columns of every design
BASELINE = CatalogueEffect("offset_and_radius", Role.ABSORBED, _offset_and_radius)
# the table design.build loops over, in column order: what is absorbed first, the wander nuisance last
CATALOGUE: tuple[CatalogueEffect, ...] = (BASELINE, softiron.TERM, channels.TERM, harmonics.TERM, wander.TERM)
_RANK = {Role.ABSORBED: 0, Role.TESTED: 1, Role.NUISANCE: 1, Role.WANDER: 2}


@dataclass(frozen=True)
class Design:
    """The columns of every candidate term at the reference model, and which group is which."""

    x: np.ndarray  # (n, p): each effect's columns in the table's order (Jacobian, soft iron, channels, harmonics, wander)
    residual_ut: np.ndarray  # (n,) the reference's radial residual with its soft iron and channel terms taken back out
    groups: dict  # tested group name → its column indices in x
    candidates: dict  # channel effect name → ChannelCandidate
    n_jacobian: int  # leading columns for offset and radius (what any refit absorbs anyway)
    n_before_wander: int  # columns before the wander nuisance (Jacobian … harmonics)
    directions: np.ndarray  # (n, 3) unit field directions (calibrated by the reference)
    offset_directions: np.ndarray  # (n, 3) W·u: how an offset change shows in the residual
    reference: ModelFit  # the model the columns were built at
    rest: np.ndarray  # (n, r) columns of tested effects along directions their tests leave out (soft iron's)
    effects: dict  # tested group name → the CatalogueEffect it belongs to
    parameter_dirs: dict  # tested group name → (p, k) the parameter combinations its columns stand for, where given

    @property
    def soft_dirs(self) -> np.ndarray:
        """(5, k) the soft-iron directions of the soft-iron group, in SOFT_BASIS coordinates."""
        return self.parameter_dirs[softiron.EFFECT]

    @property
    def coverage_gates(self) -> dict:
        """Tested group name → the share of its own a tested direction must keep (its effect's
        ``min_unique``): the coverage gate of every test of the design."""
        return {g: e.min_unique for g, e in self.effects.items()}

    @cached_property
    def x_candidates(self) -> np.ndarray:
        """Every candidate fitted: the columns before the wander nuisance and soft iron along
        the directions the tests leave out (``rest``). What the residual is judged on
        when asking whether it wanders (the twin, ladder.wander_seen): soft iron left out of
        the tests is still in the residual, and on a band of directions swept with a period it
        is a periodic signal in time — on 40 simulated band soft irons with white noise the
        Legendre check of the offset (longrun.shows_wander, at 5 %) fired on 7 beside the
        tested columns and on 3 with all five fitted, and a twin learned 0.08 µT of wander at
        the sweep's own frequency where the simulation has none."""
        return np.concatenate([self.x[:, : self.n_before_wander], self.rest], axis=1)

    @cached_property
    def basis_of_candidates(self) -> np.ndarray:
        """``column_basis`` of ``x_candidates``, made once: the twin's residual, the wander
        check and its F test all project on it."""
        return column_basis(self.x_candidates)

    @property
    def wander_cols(self) -> np.ndarray:
        return np.arange(self.n_before_wander, self.x.shape[1])

    @property
    def channel_groups(self) -> dict:
        """Channel effects other than time (time always goes through the wander gate)."""
        return {g: c for g, c in self.groups.items() if g in self.candidates and self.candidates[g].channel != channels.TIME}


def misfit_left(dsg: Design) -> np.ndarray:
    """(n,) the residual's part along the soft-iron directions the tests leave out (``rest``),
    fitted beside every candidate: fixed by the recording's geometry, in every test's residual
    and in none of the twin's draws, which are learned with it fitted."""
    if not dsg.rest.shape[1]:
        return np.zeros(len(dsg.residual_ut))
    gamma = np.linalg.lstsq(dsg.x_candidates, dsg.residual_ut, rcond=None)[0]
    return dsg.rest @ gamma[dsg.x_candidates.shape[1] - dsg.rest.shape[1]:]


def column_basis(x: np.ndarray) -> np.ndarray:
    """An orthonormal basis (n, rank) of x's column space (columns scaled to unit norm first; a
    column dependent on the others to 1e-10 adds nothing)."""
    q, r = np.linalg.qr(x / np.sqrt(np.maximum((x * x).sum(axis=0), 1e-300)))
    d = np.abs(np.diag(r))
    return q[:, d > 1e-10 * max(float(d.max(initial=0.0)), 1e-300)]


def build(m: np.ndarray, t: np.ndarray, chans: dict, ref: ModelFit, candidates: list,
          at_channels: dict | None = None, catalogue: tuple[CatalogueEffect, ...] = CATALOGUE) -> Design:
    """The design at the reference model ``ref`` (hard iron, radius and the soft iron the data
    determine) for samples ``m`` (µT), times ``t`` and channel arrays ``chans`` (keyed by
    channel name, time included as ``channels.TIME``): the columns of every effect of
    ``catalogue`` (``CATALOGUE`` unless another table is given), in its order, each tested
    group named as its effect names it; what is absorbed must come first and the wander last.

    Soft iron is tested as a Wald test of the reference's own soft-iron coordinates: the
    residual is the reference's with its soft iron taken back out to first order, so the test
    is linearised where the model fits, not at a sphere that may be far off. Its columns are
    only the directions the data determine (the reference's, softiron.determined_directions):
    along a direction they do not determine (on a band of directions, the vertical gain trades
    with the vertical offset) a linear regression slides far along a valley the nonlinear model
    does not have, and its linearisation error — slow, following the motion — is left in the
    residual of every test, whose block covariance it inflates (a 2 % soft iron on a ±15–30°
    band went from F ≈ 5 to F ≈ 120–380 once those columns were left out). The direction
    harmonics are made orthogonal to every polynomial of degree ≤ 2 on the data's own
    directions, so that on a band or any non-uniform coverage they cannot soak up soft iron.

    The channel terms are linearised where the reference was fitted: at ``at_channels``
    (channel → µT per unit, the offsets fitted beside the reference's hard iron and a full soft
    iron, ladder.with_channel_offsets; 0 for a channel not in it), and taken back out to first order
    as soft iron is, so every test is still of the term being zero. Linearised at zero, an
    offset δ that a channel switches on leaves its second-order part in the residual,
    (|δ|² − (u·δ)²)/2R while it is on: a quadratic form of the direction, soft iron's own
    signature (a current switching 11.7 µT of offset left 0.16–0.27 µT of it in the soft-iron
    test on a quiet simulated sensor, tests/test_diagnose.py)."""
    table = _in_column_order(catalogue)
    lin = linearise(m, t, chans, ref, candidates, at_channels)
    parts = [(effect, effect.columns(lin)) for effect in table]
    x = np.concatenate([c.x for _, c in parts], axis=1)
    residual = lin.residual_ut
    for _, c in parts:  # each effect's share at the reference taken back out, to first order
        if c.at_reference is not None:
            residual = residual - c.at_reference
    groups, effects, dirs = _groups(parts)
    n_jacobian = sum(c.x.shape[1] for e, c in parts if e.role is Role.ABSORBED)
    n_before_wander = sum(c.x.shape[1] for e, c in parts if e.role is not Role.WANDER)
    rests = [c.rest for _, c in parts if c.rest is not None]
    rest = np.concatenate(rests, axis=1) if rests else np.zeros((len(m), 0))
    return Design(x, residual, groups, {c.effect: c for c in candidates}, n_jacobian, n_before_wander, lin.directions,
                  lin.offset_directions, ref, rest, effects, dirs)


def linearise(m: np.ndarray, t: np.ndarray, chans: dict, ref: ModelFit, candidates: list,
              at_channels: dict | None = None) -> Linearised:
    """The point every effect's columns are made at (``build``): the residual of the model with
    soft iron along all five directions and every candidate channel, at the reference and the
    channel coefficients ``at_channels``, and its Jacobian. The soft-iron columns uᵀE_p d are
    taken at the model's own point on the surface (|h| = radius), not at the measurement: |d|
    carries the noise along the field that the residual carries too, and a regressor holding
    the residual's own noise biases its coefficient and, through the block scores, inflates
    its covariance (softiron.regressors). The directions are those of the samples with the
    channel offsets at ``at_channels`` taken out, calibrated by the reference."""
    spec = Spec(soft_iron=True, channels=tuple(c.channel for c in candidates))
    at = at_channels or {}
    coefs = np.concatenate([np.zeros(0)] + [np.asarray(at.get(c.channel, np.zeros(3)), np.float64) for c in candidates])
    params = np.concatenate([ref.offset_ut, ref.soft, [ref.field_ut], coefs])
    residual, jac = residual_jacobian(params, spec, m, [chans[c.channel] - c.reference for c in candidates])
    jac[:, 3:8] *= (ref.field_ut / (residual + ref.field_ut))[:, None]
    shift = sum((np.outer(chans[c.channel] - c.reference, at[c.channel]) for c in candidates if c.channel in at),
                np.zeros_like(m))
    h = ref.calibration().correct(m - shift)  # the directions where the design is linearised
    u = h / np.linalg.norm(h, axis=1, keepdims=True)
    return Linearised(m, t, chans, ref, tuple(candidates), coefs, residual, jac, u, -jac[:, 0:3])


def _in_column_order(catalogue) -> tuple[CatalogueEffect, ...]:
    """The table, checked: what any refit absorbs leads (the design's ``n_jacobian``) and the
    wander nuisance trails (``n_before_wander``), so both are counts of leading columns."""
    table = tuple(catalogue)
    ranks = [_RANK[e.role] for e in table]
    if ranks != sorted(ranks):
        raise ValueError("a design's table lists what is absorbed first and the wander nuisance last; got "
                         + ", ".join(f"{e.name} ({e.role.value})" for e in table))
    return table


def _groups(parts: list) -> tuple[dict, dict, dict]:
    """Each tested group's column indices in the design, its effect and its parameter
    directions (where its effect gives them), from each effect's columns in table order."""
    groups, effects, dirs, start = {}, {}, {}, 0
    for effect, c in parts:
        at = start
        for name, width in c.groups:
            if name in groups:
                raise ValueError(f"two tested groups of the design are both named {name!r}")
            groups[name], effects[name], at = np.arange(at, at + width), effect, at + width
            if c.parameter_dirs is not None:
                dirs[name] = c.parameter_dirs
        start += c.x.shape[1]
    return groups, effects, dirs


def test_against_rich_wander(design: Design, t: np.ndarray, null: tuple | None) -> dict:
    """Each channel tested a second time against a rich wander nuisance (Legendre degrees
    2..RICH_DEGREE of the offset vs time). A channel that varies faster than the wander (an
    intermittent current) keeps most of its variation and needs no wander gate; a slow one (a
    temperature cycle) is absorbed and left to the first test and the gate. Each test is run on
    the twin's draws ``null`` ((n, K) with and without its wander) too and judged against them (inference.calibrated).
    Returns effect → WaldResult."""
    groups = design.channel_groups
    if not groups:
        return {}
    # on a systematic subsample of at most RICH_MAX rows: the wide design stays small in memory
    sel = slice(None, None, max(1, -(-len(design.residual_ut) // RICH_MAX)))
    x_rich = np.concatenate(
        [design.x[sel, : design.n_before_wander], wander.regressors(t[sel], design.directions[sel], RICH_DEGREE)], axis=1
    )
    results = block_wald(x_rich, design.residual_ut[sel], groups, null=None if null is None else tuple(v[sel] for v in null))
    return {g: calibrated(r) for g, r in results.items()}


def full_candidate_calibration(design: Design):
    """The reference calibration with every candidate channel term added, each coefficient from
    the one regression on all of the design's columns: the model the recording's twin is
    learned around (magcal.diagnose.null), so that an effect that is there is not taken for
    wander."""
    beta = np.linalg.lstsq(design.x, design.residual_ut, rcond=None)[0]
    cal = design.reference.calibration()
    coef = dict(cal.coef_ut_per_unit)
    ref = dict(cal.reference)
    for g, cand in design.candidates.items():
        coef[cand.channel] = -beta[design.groups[g]]
        ref[cand.channel] = cand.reference
    return Calibration(offset_ut=cal.offset_ut, field_ut=cal.field_ut, soft_iron=cal.soft_iron,
                       coef_ut_per_unit=coef, reference=ref)
