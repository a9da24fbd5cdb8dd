"""The tracker: the calibration in force at every moment, from the samples so far.

A sensor's calibration wanders (the offset follows temperature, current and ageing; a mount's
soft iron can change), so a calibration fitted once goes stale. ``Tracker`` keeps a full
ellipsoid up to date as samples arrive, with bounded memory and bounded time per sample:

* **Memory: the coverage-balanced buffer** (``cell_buffer.CellBuffer``, ``WhenFull.THIN``): each
  equal-area direction cell keeps ``per_cell`` samples with their times, spread over the time
  it was visited. A direction visited again thins its own samples; a direction not visited for
  a long time keeps its last ones, so the shape stays pinned in directions the recent motion
  does not reach. Memory is ``cells × per_cell`` samples, whatever the length of the stream.
* **Weights: each cell counts the same** (a share floor, as ``select.direction_weights``), so
  lingering in a few poses cannot bend the ellipsoid; and **older samples count less** at a
  rate estimated from the data: the radial residual of a sample of age a is modelled as
  N(0, s² + q·a) (s: noise and shape error; q: how fast the calibration wanders, µT²/s), and
  (s², q) are the maximum-likelihood values on the buffer's own residuals. A still sensor gives
  q ≈ 0 and the buffer is one long memory; a wandering one gives q > 0 and weight 1/(1 + q a/s²).
* **Solve: a few weighted Gauss–Newton steps** of the geometric (ML) residual
  ``geometric.residual`` every ``refit_every`` samples but at most once per ``refit_min_s`` of
  sample time (the wander it follows lasts seconds to hours, so a faster sensor does not need
  more refits a second: the cost per second of stream is bounded whatever the rate), started
  from the previous solution, with Huber weights against spikes. The model grows sphere →
  diagonal → full ellipsoid when the buffer's coverage determines it (information condition,
  the sphere's limit for every model, and shape σ), checked at most every ``grow_every``
  samples; a calibration *reported* is judged by fit's own gates (``tracker_check``).
* **A field the Earth could give.** A first solution is also refused when its field is below
  ``min_field_ut`` (the Earth's 15 µT, ``EARTH_FIELD_UT``). A board that has hardly turned yet
  gives a small cloud of noisy samples, and a sphere of a few µT wraps such a cloud with every
  direction covered: its condition passes, and its offset is one field radius from the truth.
  A running solution that shrinks below the floor is withdrawn.
* **A centre the samples pin.** A first solution is also refused when its centre could move by
  a fifth of the field along the samples' thinnest axis, the sphere refitted about it, for less
  than 2σ of likelihood (``centre_shift_chi2``). Samples near a circle — flat turns where the
  field dips — lie on every sphere through that circle; the one found first is the sphere whose
  equator the circle is, and at it the information matrix looks well conditioned while its
  centre is tens of µT off along the circle's axis.

Nothing here keeps the whole history or refits it: per sample one cell lookup and one buffer
write; per refit O(cells × per_cell). ``Tracker.add`` returns a new :class:`Estimate` when the
calibration in force changed (it holds for the samples after ``Estimate.sample``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.calibration import EARTH_FIELD_UT, Calibration
from . import geometric, tails
from .accumulator import check_state, renamed_keys
from .ellipsoid import algebraic_start
from .failure import FitFailure
from .pipeline import DEFAULT_MAX_CONDITION, DEFAULT_MAX_SHAPE_SIGMA
from .result import MODEL_NAMES
from .sphere import sphere_start
from .cell_buffer import CellBuffer, WhenFull
from .tracker_memory import WanderRate, robust_scale, sample_weights
from .uncertainty import direction_jackknife_variance, gain_widening, shape_sigma

_OLD_NAMES = {"ladder_every": "grow_every", "last_ladder": "last_growth", "cells_at_ladder": "cells_at_growth"}
CHANGE_ALPHA = 1e-9  # a sudden change is declared at this false-alarm probability per refit
CHANGE_MIN_PAIRS = 5
CHANGE_MIN_EVIDENCE = 200  # pairs in the wander record before its model judges a change
START_MARGIN = 10.0  # a first solution needs 10× the conditioning a running one needs (hysteresis)
PIN_SHIFT = 0.2  # a first solution's centre must be pinned to this share of its field (a heading within ~11°)…
PIN_CHI2 = 4.0  # …at 2σ: moving it that far along the samples' thinnest axis must cost this much likelihood
HUBER_K = 2.5  # Huber threshold in robust σ of the residual (95 % efficiency under Gaussian noise)
_STATE_KIND = "magcal.tracker"
_STATE_VERSION = 1


@dataclass(frozen=True)
class TrackerConfig:
    """How the tracker keeps its memory and how often it solves (see the module docstring)."""

    bands: int = 8
    sectors: int = 16
    per_cell: int = 8
    refit_every: int = 20
    refit_min_s: float = 0.4
    grow_every: int = 200
    min_samples: int = 20
    min_share: float = 0.1
    max_condition: float = DEFAULT_MAX_CONDITION
    max_shape_sigma: float = DEFAULT_MAX_SHAPE_SIGMA
    min_field_ut: float = EARTH_FIELD_UT[0]

    def __post_init__(self):
        ints = ("bands", "sectors", "per_cell", "refit_every", "grow_every", "min_samples")
        for name in ints:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"tracker {name} must be ≥ 1, not {getattr(self, name)!r}")
        if not (math.isfinite(self.refit_min_s) and self.refit_min_s >= 0.0):
            raise ValueError(f"tracker refit_min_s must be finite and ≥ 0, not {self.refit_min_s!r}")
        if not 0.0 <= self.min_share <= 1.0:
            raise ValueError(f"tracker min_share must be in [0, 1], not {self.min_share!r}")
        if not (math.isfinite(self.min_field_ut) and self.min_field_ut >= 0.0):
            raise ValueError(f"tracker min_field_ut must be finite and ≥ 0, not {self.min_field_ut!r}")

    @property
    def capacity(self) -> int:
        return self.bands * self.sectors * self.per_cell


@dataclass(frozen=True)
class Estimate:
    """The calibration in force after sample ``sample`` (0-based, samples given to the tracker).

    ``wander_ut2_per_s``: q, the variance growth rate of the radial error with age (0 = the
    data show no wander); ``noise_ut``: s, the residual scale of fresh samples;
    ``offset_sigma_ut``: 1σ of the offset from the weighted fit, at least the delete-a-face
    jackknife's over the directions in memory (``direction_widening``) and, on a sphere, with what
    axis gains it takes as equal would do to it (``gain_widening``);
    ``buffered``: samples in memory; ``coverage``: share of direction cells holding any.
    A *reported* estimate (``tracker_check.checked``) also states ``field_sigma_ut`` and
    ``soft_iron_sigma`` (3×3), each at least fit's on the same samples, and ``refused_model``: the
    model the tracker ran that fit's gates refused there (None: none was).
    """

    sample: int
    t_s: float
    model: str
    calibration: Calibration
    wander_ut2_per_s: float
    noise_ut: float
    offset_sigma_ut: np.ndarray = field(repr=False)
    buffered: int
    coverage: float
    field_sigma_ut: float = math.nan
    soft_iron_sigma: np.ndarray | None = field(default=None, repr=False)
    refused_model: str | None = None

    def to_dict(self) -> dict:
        c = self.calibration
        return {
            "sample": self.sample,
            "t": self.t_s,
            "model": self.model,
            "offset_ut": [float(v) for v in c.offset_ut],
            "soft_iron": [[float(v) for v in row] for row in c.soft_iron],
            "field_ut": c.field_ut,
            "offset_sigma_ut": [float(v) if math.isfinite(v) else None for v in self.offset_sigma_ut],
            "wander_ut2_per_s": self.wander_ut2_per_s,
            "noise_ut": self.noise_ut,
            "buffered": self.buffered, "coverage": self.coverage,
            "field_sigma_ut": self.field_sigma_ut if math.isfinite(self.field_sigma_ut) else None,
            "soft_iron_sigma": None if self.soft_iron_sigma is None else np.asarray(self.soft_iron_sigma).tolist(),
            "refused_model": self.refused_model,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Estimate":
        """The inverse of ``to_dict``."""
        return cls(
            sample=int(d["sample"]), t_s=float(d["t"]), model=str(d["model"]),
            calibration=Calibration(offset_ut=d["offset_ut"], field_ut=d["field_ut"], soft_iron=d["soft_iron"]),
            wander_ut2_per_s=float(d["wander_ut2_per_s"]), noise_ut=float(d["noise_ut"]),
            offset_sigma_ut=np.array([np.inf if v is None else v for v in d["offset_sigma_ut"]], dtype=np.float64),
            buffered=int(d["buffered"]), coverage=float(d["coverage"]),
            field_sigma_ut=math.nan if d.get("field_sigma_ut") is None else float(d["field_sigma_ut"]),
            soft_iron_sigma=None if d.get("soft_iron_sigma") is None else np.asarray(d["soft_iron_sigma"], float),
            refused_model=d.get("refused_model"),
        )


@dataclass(frozen=True)
class Withdrawal:
    """No calibration is in force after sample ``sample`` any more, and why."""

    sample: int
    t_s: float
    reason: str

    def to_dict(self) -> dict:
        return {"sample": self.sample, "t": self.t_s, "model": None, "offset_ut": None, "soft_iron": None,
                "field_ut": None, "reason": self.reason}


def condition(A: np.ndarray) -> float:
    """Condition number of an information matrix JᵀWJ scaled to unit diagonal (the test of
    ``uncertainty.information_condition``, from the normal matrix)."""
    d = np.sqrt(np.diag(A))
    if np.any(d <= 0) or not np.all(np.isfinite(d)):
        return float("inf")
    ev = np.linalg.eigvalsh(A / np.outer(d, d))
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def _damped_step(pts, kind, theta, w, e, J, lam: float):
    """One damped Gauss–Newton step of Σ w e² from θ (residual e, Jacobian J there;
    ``geometric.damped_step``, at most six dampings, the radius kept positive). Returns
    (θ, Σ w e², damping, JᵀWJ at the start); θ is unchanged when no step lowers the sum."""
    cost = float(w @ (e * e))
    Jw = J * w[:, None]
    A, g = J.T @ Jw, Jw.T @ e

    def evaluate(trial):
        if not trial[3] > 0:
            return np.inf, None
        with np.errstate(over="ignore", invalid="ignore"):  # a wild trial: its cost is not finite, refused
            e2 = geometric.residual(trial, pts, kind)
            return float(w @ (e2 * e2)), None

    step = geometric.damped_step(evaluate, theta, A, g, cost, lam, max_tries=6)
    if step is None:
        return theta, cost, lam * 1e6, A
    return step.x, step.cost, max(step.lam / 10.0, 1e-9), A


def _shifted_sphere_cost(m, w, centre, u, r0: float, steps: int = 20) -> float:
    """Σ w e² of the best sphere whose centre is ``centre`` moved within the plane spanned by
    ``u`` (3×2), radius free (``geometric.levenberg_marquardt`` from the plane's origin and r0)."""
    sw = np.sqrt(w)

    def fun(p):
        return sw * (np.linalg.norm(m - (centre + u @ p[:2]), axis=1) - p[2])

    def jac(p):
        d = m - (centre + u @ p[:2])
        nd = np.linalg.norm(d, axis=1)
        return sw[:, None] * np.column_stack([-(d @ u) / nd[:, None], -np.ones(len(m))])

    p, _, _ = geometric.levenberg_marquardt(fun, jac, [0.0, 0.0, r0], max_iter=steps)
    e = fun(p)
    return float(e @ e)


def centre_shift_chi2(m, w, theta, cost: float, shift: float = PIN_SHIFT) -> float:
    """How much likelihood (Σw·ln of the cost ratio, χ² with 1 degree of freedom) it costs to move
    the sphere θ's centre by ``shift`` × its field along the samples' thinnest axis, the sphere
    refitted about it; ``cost`` is θ's own Σ w e² (θ converged). Small: the centre is not pinned."""
    mu = (w @ m) / w.sum()
    _, axes = np.linalg.eigh(((m - mu) * w[:, None]).T @ (m - mu))
    moved = min(_shifted_sphere_cost(m, w, theta[:3] + sign * shift * theta[3] * axes[:, 0], axes[:, 1:], theta[3])
                for sign in (1.0, -1.0))
    return float(w.sum() * np.log(max(moved, cost) / max(cost, 1e-300)))


def gauss_newton(pts, kind, theta, w, steps: int):
    """``steps`` damped Gauss–Newton steps (``_damped_step``) from θ. Returns (θ, JᵀWJ at the
    result, Σ w e²)."""
    lam = 1e-6
    e, J = geometric.residual_jacobian(theta, pts, kind)
    cost = float(w @ (e * e))
    for _ in range(steps):
        moved, cost, lam, _ = _damped_step(pts, kind, theta, w, e, J, lam)
        if moved is theta:
            break
        theta = moved
        e, J = geometric.residual_jacobian(theta, pts, kind)
    return theta, J.T @ (J * w[:, None]), cost


def _extend(theta: np.ndarray, kind: str) -> np.ndarray:
    """θ of a smaller model as the same ellipsoid in ``kind``'s parameters (the parameter
    vectors are nested: sphere [b, r] ⊂ diagonal [.., s_xx, s_yy] ⊂ full [.., s_xy, s_xz, s_yz])."""
    out = np.zeros(geometric.n_params(kind))
    out[: len(theta)] = theta
    return out


def direction_widening(J, e, w, A, s2: float) -> np.ndarray:
    """Per offset axis, how much wider than the weighted fit's σ the delete-a-face jackknife
    over the buffer's directions is (≥ 1; ``uncertainty.direction_jackknife_variance``, its
    leverage share kept as a floor): the answer moves with which directions memory holds, which
    the fresh-sample noise does not count (on the real recordings the final offsets of two
    halves differed by 2.5× their 95 % intervals without it)."""
    jk = direction_jackknife_variance(J, e, w)
    if jk is None:
        return np.ones(3)
    try:
        var = np.diag(np.linalg.inv(A))[:3] * s2  # the σ ``_publish`` states before widening
    except np.linalg.LinAlgError:
        return np.ones(3)
    return np.maximum(np.sqrt(np.clip(jk[:3], 0.0, None) / np.clip(var, 1e-300, None)), 1.0)


class Tracker:
    """Follows the calibration of one sensor through a stream of samples (µT, seconds)."""

    def __init__(self, config: TrackerConfig | None = None):
        self.config = c = config or TrackerConfig()
        self.memory = CellBuffer(c.bands, c.sectors, c.per_cell, when_full=WhenFull.THIN, min_share=c.min_share)
        self.wander = WanderRate()
        self.n = 0  # samples offered (the index of the next one)
        self.skipped = 0  # non-finite samples refused
        self.changes = 0  # sudden changes seen
        self._suspect = False  # the last refit's new samples looked like a change
        self._jumps: dict[int, float] = {}  # epoch → its step squared (µT²)
        self.kind: str | None = None
        self.theta: np.ndarray | None = None
        self.estimate: Estimate | None = None
        self._since_refit = 0
        self._damping = 1e-6
        self._seq_at_refit = 0
        self._last_growth = -(10**18)
        self._cells_at_growth = 0
        self._t_last = 0.0
        self._t_refit = -math.inf  # sample time of the last refit
        self._sum = [0.0, 0.0, 0.0]
        self.n_used = 0
        self.low_field_ut: float | None = None  # set when the last first solution was refused for its field
        self.solved = None  # (model, θ, JᵀWJ, s²) of the last estimate published (``tracker_check``)

    def coverage(self) -> float:
        return self.memory.coverage()

    # -- the stream ----------------------------------------------------------------------
    def add(self, m_ut, t_s: float) -> Estimate | Withdrawal | None:
        """Offer one sample (µT, s); returns the new Estimate when the calibration in force
        changed (a Withdrawal when there is none any more). A non-finite sample is counted in
        ``skipped`` and otherwise ignored."""
        x, y, z = (float(v) for v in m_ut)
        t = float(t_s)
        self.n += 1
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z) and math.isfinite(t)):
            self.skipped += 1
            return None
        self.memory.add(x, y, z, t)  # (the first sample is the centre of directions until a solution)
        self._t_last = t
        s = self._sum
        s[0] += x
        s[1] += y
        s[2] += z
        self.n_used += 1
        self._since_refit += 1
        if self._since_refit < self.config.refit_every or 0.0 <= t - self._t_refit < self.config.refit_min_s - 1e-6:
            return None  # (times to 1 µs, below any sample clock's step; a clock that went back holds nothing off)
        self._since_refit, self._t_refit = 0, t
        return self._refit()

    def add_many(self, m_ut, t_s) -> list[Estimate | Withdrawal]:
        """Offer (n, 3) samples with times (n,); the changes of the calibration in force."""
        m = np.asarray(m_ut, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        if len(t) != len(m):
            raise ValueError(f"{len(m)} samples but {len(t)} times")
        out = []
        for row, tt in zip(m.tolist(), t.tolist()):
            e = self.add(row, tt)
            if e is not None:
                out.append(e)
        return out

    # -- solving -------------------------------------------------------------------------
    def _start(self) -> bool:
        """First solution: the algebraic sphere of the buffer (filed about the samples' mean)
        refined to the ML sphere, kept only if the buffer's coverage pins it."""
        self.memory.rebin(np.array(self._sum) / self.n_used, force=True)
        _, m, _, wc = self.memory.samples()
        start = sphere_start(m, max_condition=100 * self.config.max_condition)
        if isinstance(start, FitFailure):
            return False
        theta, A, _ = gauss_newton(m, "sphere", np.asarray(start, dtype=np.float64), wc, 10)
        self.low_field_ut = None
        if condition(A) > self.config.max_condition / START_MARGIN:
            return False
        if theta[3] < self.config.min_field_ut:
            self.low_field_ut = float(theta[3])
            return False
        theta, _, cost = gauss_newton(m, "sphere", theta, wc, 20)  # converged, for the likelihood ratio
        if centre_shift_chi2(m, wc, theta, cost) < PIN_CHI2:
            return False
        self.theta, self.kind = theta, "sphere"
        self.memory.rebin(theta[:3], force=True)
        self._seq_at_refit = self.memory.seq_count
        return True

    def _weights(self, idx, t, wc, e) -> tuple[np.ndarray, float, float]:
        """Cell balance × age × Huber from the residuals e under the calibration in force;
        returns (w with mean 1, s², q). The wander q is learnt first from the new samples
        (``WanderRate``), then ``tracker_memory.sample_weights``."""
        scale = robust_scale(e)
        d, delta, other, dt = self.memory.pairs(idx, e, self._seq_at_refit, self.theta[:3])
        self._seq_at_refit = self.memory.seq_count
        if not self._changed(d, delta, other, dt, scale):
            self.wander.add(np.clip(d, -HUBER_K * scale, HUBER_K * scale), delta, other, dt)
        _, q = self.wander.solve()
        w, s2 = self.weights_now(idx, t, wc, e, q)
        self.memory.rho_per_s = q / s2
        return w, s2, q

    def weights_now(self, idx, t, wc, e, q: float) -> tuple[np.ndarray, float]:
        """(w, s²) of the memory's samples ``idx`` from their residuals ``e``, at wander rate q."""
        steps = self._jump_ratio(self.memory.epoch_of[idx], 1.0)
        return sample_weights(e, np.maximum(self._t_last - t, 0.0), wc, q, steps, HUBER_K)

    def _changed(self, d, delta, other, dt, scale) -> bool:
        """Did the sensor change at once (a payload's magnet, a knock)? Most new samples differ
        from the older ones of their own cells far beyond what the wander model expects: the
        median of d²/v above the level that k draws of χ²₁ pass with probability
        ``CHANGE_ALPHA`` (the median, so that glitches and heavy tails cannot trigger it; a
        change moves them all). The samples from before then count as far off as the jump
        (``_jump_ratio``) and pairs no longer reach across it; nothing is thrown away."""
        v = self.wander.variance(delta, other, dt)
        k = len(d)
        if v is None or k < CHANGE_MIN_PAIRS or self.wander.n < CHANGE_MIN_EVIDENCE:
            return False
        half = k // 2 + 1
        level = tails.chi2_isf(tails.beta_ppf(CHANGE_ALPHA, half, k - half + 1), 1)
        if np.sort(d * d / v)[k - half] <= level:
            self._suspect = False
            return False
        if not self._suspect:  # a change lasts: it must show again in the next samples
            self._suspect = True
            return True  # (these pairs stay out of the wander record)
        self._suspect = False
        self._jumps[self.memory.epoch] = float(np.median(d * d))  # µT²: the step, squared
        self.memory.epoch += 1
        self.changes += 1
        return True

    def _jump_ratio(self, epochs: np.ndarray, s2: float) -> np.ndarray:
        """Per sample, the squared steps since it came, in units of s²."""
        if not self._jumps:
            return np.zeros(len(epochs))
        old = int(epochs.min()) if len(epochs) else self.memory.epoch
        self._jumps = {e: j for e, j in self._jumps.items() if e >= old}  # no sample left from before
        steps = np.zeros(self.memory.epoch + 1)
        for e, j in self._jumps.items():
            steps[: e + 1] += j
        return steps[epochs] / s2

    def _grow(self, m, w) -> None:
        """Try the fuller models, each from the current one and from the algebraic ellipsoid;
        kept if determinable (information condition) and its gains pinned (shape σ from its own
        residual), as ``pipeline`` judges them. A new model starts a new wander record."""
        c = self.config
        self._last_growth, self._cells_at_growth = self.n, self.memory.occupied()
        for kind in geometric.KINDS[geometric.KINDS.index(self.kind) + 1:]:
            best = None
            for start in (_extend(self.theta, kind), algebraic_start(m, kind)):
                if isinstance(start, FitFailure):
                    continue
                fitted = gauss_newton(m, kind, np.asarray(start, dtype=np.float64), w, 8)
                if best is None or fitted[2] < best[2]:
                    best = fitted
            theta, A, cost = best
            if condition(A) > c.max_condition:
                return
            cov = (cost / max(len(m) - len(theta), 1)) * np.linalg.pinv(A)
            if shape_sigma(cov) > c.max_shape_sigma:
                return
            self.theta, self.kind = theta, kind
            self.wander = WanderRate()

    def _refit(self) -> Estimate | Withdrawal | None:
        if self.memory.valid.sum() < max(self.config.min_samples, 5):
            return None
        if self.theta is None and not self._start():
            return None
        idx, m, t, wc = self.memory.samples()
        e, J = geometric.residual_jacobian(self.theta, m, self.kind)
        if condition(J.T @ (J * wc[:, None])) > self.config.max_condition:
            return self._withdraw()
        w, s2, q = self._weights(idx, t, wc, e)
        if self.kind != "full" and (self.n - self._last_growth >= self.config.grow_every
                                    or self.memory.occupied() > self._cells_at_growth):
            self._grow(m, w)
            e, J = geometric.residual_jacobian(self.theta, m, self.kind)
        theta, _, self._damping, A = _damped_step(m, self.kind, self.theta, w, e, J, self._damping)
        if theta is self.theta or condition(A) > self.config.max_condition:
            return None  # no better solution, or the weighted buffer no longer pins this model
        if theta[3] < self.config.min_field_ut:
            self.low_field_ut = float(theta[3])
            return self._withdraw(f"the field the samples give, {theta[3]:.3g} µT, is below the Earth's "
                                  f"{self.config.min_field_ut:.3g} µT")
        self.theta = theta
        if np.linalg.norm(theta[:3] - self.memory.centre_ut) > 0.1 * theta[3]:
            self.memory.rebin(theta[:3])
        widen = direction_widening(J, e, w, A, s2)
        return self._publish(A, s2, q, len(m), gain_widening(theta, m, A, s2, widen) if self.kind == "sphere" else widen)

    def _withdraw(self, reason: str = "the samples in memory no longer determine the calibration "
                                      "(too few directions)") -> Withdrawal | None:
        """The memory no longer pins the model in force (a first solution that looked pinned
        on few samples): back to no calibration, said once."""
        had = self.estimate is not None
        self.theta, self.kind, self.estimate, self.wander = None, None, None, WanderRate()
        return Withdrawal(sample=self.n - 1, t_s=self._t_last, reason=reason) if had else None

    def _publish(self, A, s2, q, n_buf, widen=None) -> Estimate:
        b, r, W = geometric.unpack(self.theta, self.kind)
        try:
            sig = np.sqrt(np.clip(np.diag(s2 * np.linalg.inv(A))[:3], 0.0, None)) * (1.0 if widen is None else widen)
        except np.linalg.LinAlgError:
            sig = np.full(3, np.inf)
        self.solved = (self.kind, self.theta, A, s2)
        self.estimate = Estimate(
            sample=self.n - 1, t_s=self._t_last, model=MODEL_NAMES[self.kind],
            calibration=Calibration(offset_ut=b, field_ut=r, soft_iron=W),
            wander_ut2_per_s=q, noise_ut=math.sqrt(s2), offset_sigma_ut=sig,
            buffered=n_buf, coverage=self.coverage(),
        )
        return self.estimate

    # -- persistence -----------------------------------------------------------------------
    def to_state(self) -> dict:
        """JSON-able state; ``Tracker.from_state`` continues exactly where this one stopped."""
        c = self.config
        return {
            "kind": _STATE_KIND, "version": _STATE_VERSION,
            "config": {f: getattr(c, f) for f in c.__dataclass_fields__},
            "memory": self.memory.to_state(), "wander": self.wander.to_state(),
            "n": self.n, "skipped": self.skipped, "changes": self.changes,
            "jumps": [[e, j] for e, j in self._jumps.items()], "suspect": self._suspect, "n_used": self.n_used, "sum": list(self._sum),
            "model": self.kind, "theta": None if self.theta is None else self.theta.tolist(),
            "since_refit": self._since_refit, "damping": self._damping, "seq_at_refit": self._seq_at_refit,
            "last_growth": self._last_growth, "cells_at_growth": self._cells_at_growth, "t_last": self._t_last,
            "t_refit": self._t_refit if math.isfinite(self._t_refit) else None,
            "estimate": None if self.estimate is None else self.estimate.to_dict(),
            "low_field_ut": self.low_field_ut,
        }

    @classmethod
    def from_state(cls, d: dict) -> "Tracker":
        check_state(d, _STATE_KIND, _STATE_VERSION, "tracker")
        try:
            d = renamed_keys(d, _OLD_NAMES)  # a state saved before the growth had its name
            trk = cls(TrackerConfig(**d["config"]))
            trk.memory.load_state(d["memory"])
            trk.wander = WanderRate.from_state(d["wander"])
            trk.n, trk.skipped, trk.n_used = int(d["n"]), int(d["skipped"]), int(d["n_used"])
            trk.changes, trk._jumps = int(d["changes"]), {int(e): float(j) for e, j in d["jumps"]}
            trk._suspect = bool(d["suspect"])
            trk._sum = [float(v) for v in d["sum"]]
            trk.kind = d["model"]
            trk.theta = None if d["theta"] is None else np.asarray(d["theta"], dtype=np.float64)
            trk._since_refit, trk._damping = int(d["since_refit"]), float(d["damping"])
            trk._seq_at_refit, trk._last_growth = int(d["seq_at_refit"]), int(d["last_growth"])
            trk._cells_at_growth, trk._t_last = int(d["cells_at_growth"]), float(d["t_last"])
            t_refit = d.get("t_refit")  # (absent from states saved before the refit spacing)
            trk._t_refit = -math.inf if t_refit is None else float(t_refit)
            trk.estimate = None if d["estimate"] is None else Estimate.from_dict(d["estimate"])
            low = d.get("low_field_ut")  # (absent from states saved before the field floor)
            trk.low_field_ut = None if low is None else float(low)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"tracker state is malformed: {exc}") from None
        if trk.kind not in (None, *geometric.KINDS) or (trk.theta is not None and len(trk.theta) != geometric.n_params(trk.kind)):
            raise ValueError("tracker state is inconsistent (model and parameters disagree)")
        return trk


@dataclass(frozen=True)
class Comparison:
    """How much better the tracker's calibration fits the samples in memory than another one.

    Both are judged on the same samples with the tracker's own weights (each direction cell the
    same, older samples less at the wander rate), by the relative radial error e = |h|/mean|h| − 1
    (scale-free, as the field's spread). ``gain``: mean over cells of e_other² − e_ours²
    (positive: ours is better); ``sigma``: its standard error from the spread of the per-cell
    differences (cells are the independent units: a direction's error persists, so samples
    within a cell do not count as independent); ``z`` = gain / sigma. RMS figures in %."""

    rms_other_pct: float
    rms_ours_pct: float
    gain: float
    sigma: float
    cells: int

    @property
    def z(self) -> float:
        return self.gain / self.sigma if self.sigma > 0 else (math.inf if self.gain > 0 else 0.0)

    def to_dict(self) -> dict:
        return {"rms_other_pct": self.rms_other_pct, "rms_ours_pct": self.rms_ours_pct, "gain": self.gain,
                "sigma": self.sigma, "z": self.z if math.isfinite(self.z) else None, "cells": self.cells}


def compare(tracker: "Tracker", other: Calibration, ours: Estimate | None = None) -> Comparison | None:
    """``Comparison`` of ``ours`` (else the tracker's estimate) with ``other`` on its memory (None: none)."""
    est = ours or tracker.estimate
    if est is None:
        return None
    slots, m, t, wc = tracker.memory.samples()
    rho = tracker.memory.rho_per_s
    w = wc / (1.0 + rho * np.maximum(tracker._t_last - t, 0.0))

    def rel_err2(cal: Calibration) -> np.ndarray:
        h = np.linalg.norm((m - cal.offset_ut) @ cal.soft_iron.T, axis=1)
        return (h / (w @ h / w.sum()) - 1.0) ** 2

    d = rel_err2(other) - rel_err2(est.calibration)
    cells = slots // tracker.config.per_cell
    wsum = np.bincount(cells, weights=w)
    occ = np.flatnonzero(wsum > 0)
    d_cell = np.bincount(cells, weights=w * d)[occ] / wsum[occ]
    W = wsum[occ] / wsum[occ].sum()
    gain = float(W @ d_cell)
    k = len(occ)
    var = float(W**2 @ (d_cell - gain) ** 2) * k / max(k - 1, 1)
    return Comparison(
        rms_other_pct=100 * math.sqrt(float(w @ rel_err2(other) / w.sum())),
        rms_ours_pct=100 * math.sqrt(float(w @ rel_err2(est.calibration) / w.sum())),
        gain=gain, sigma=math.sqrt(var), cells=k,
    )
