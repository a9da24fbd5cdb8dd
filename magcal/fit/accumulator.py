"""The sphere accumulator: running sums of the 4×4 normal equations, O(1) per sample.

Model (algebraic sphere, the seed's normal equations done right)::

    |m − c|² = r²   ⇔   |y|² = 2 c'·y + d     with y = m − ref, c' = c − ref, d = r² − |c'|²

Least squares on the algebraic residual |y|² − 2c'·y − d needs only the moments of y::

    n, Σy (3), Σyyᵀ (3×3), Σy|y|² (3), Σ|y|⁴

all kept in float64 about a reference point ``ref`` (the first sample unless given), so a
sensor thousands of counts from the origin loses no precision: the sums never hold |m|³ of a
far-away point, only |m − ref|³ of a point on a sphere of radius ~50 µT. Accumulators with
different references merge exactly by the binomial shift of these moments.

Solving re-centres the moments on the sample mean, scales them isotropically and checks the
condition of the normal matrix (rotation-invariant: the ratio of the spread along the
best- and worst-covered directions) before solving. The result is a :class:`SphereFit` or a
:class:`~magcal.fit.failure.FitFailure` — never a half-built model.

>>> import numpy as np
>>> u = np.random.default_rng(0).normal(size=(200, 3))
>>> m = 50 * u / np.linalg.norm(u, axis=1, keepdims=True) + [900.0, -450.0, 300.0]
>>> acc = SphereAccumulator(); acc.add_batch(m)
>>> fit = acc.solve()
>>> bool(np.allclose(fit.offset_ut, [900, -450, 300])), round(fit.field_ut, 6)
(True, 50.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.calibration import Calibration
from .failure import FitFailure

DEFAULT_MIN_SAMPLES = 10
DEFAULT_MAX_CONDITION = 300.0  # ±5° tilt ≈ 170; flat turns ≈ 700 (simulated)
MAX_RMS_OVER_SPREAD = 0.25  # a sphere's residual is far below the samples' spread; a still cloud's is not
# ... but only a cloud is judged so: turning a board ~20° in the weakest Earth field (15 µT) spreads its
# samples this far, and samples that spread further moved — a residual that is large against their
# spread then says the data hold a faulty stretch (a swapped, stuck or clipped axis), not that the
# board was held still, and the robust fits that start from this sphere deal with it
CLOUD_MAX_SPREAD_UT = 5.0
_STATE_KIND = "magcal.sphere_accumulator"
_STATE_VERSION = 1


def check_state(d, kind: str, version: int, what: str) -> None:
    """Raise ValueError naming ``what`` unless ``d`` is a saved state of this kind and version."""
    if not isinstance(d, dict) or d.get("kind") != kind:
        raise ValueError(f"not a {what} state (kind must be {kind!r})")
    if d.get("version") != version:
        raise ValueError(f"{what} state version {d.get('version')!r} is not {version}")


def renamed_keys(d: dict, names: dict) -> dict:
    """``d`` (and the dicts in it) with each key saved under an older name in ``names`` given its new one."""
    return {names.get(k, k): renamed_keys(v, names) if isinstance(v, dict) else v for k, v in d.items()}


@dataclass(frozen=True)
class SphereFit:
    """An algebraic sphere: centre ``offset_ut`` (3,), radius ``field_ut``.

    ``condition``: condition number of the centred, scaled normal matrix (≥ 1; large = thin
    coverage). ``rms_algebraic_ut2``: RMS of |m − c|² − r² (µT²); ``rms_ut`` ≈ that / 2r, the
    first-order geometric RMS. ``offset_sigma_ut``: 1σ of the offset from the algebraic
    residual (a quick estimate; the ML fits report the proper one).
    """

    offset_ut: np.ndarray
    field_ut: float
    condition: float
    n: int
    rms_algebraic_ut2: float
    offset_sigma_ut: np.ndarray

    @property
    def rms_ut(self) -> float:
        return self.rms_algebraic_ut2 / (2.0 * self.field_ut)

    @property
    def calibration(self) -> Calibration:
        return Calibration(offset_ut=self.offset_ut, field_ut=self.field_ut)

    def __bool__(self) -> bool:
        return True

    def to_dict(self) -> dict:
        return {
            "offset_ut": [float(v) for v in self.offset_ut],
            "field_ut": float(self.field_ut),
            "condition": float(self.condition),
            "n": int(self.n),
            "rms_algebraic_ut2": float(self.rms_algebraic_ut2),
            "offset_sigma_ut": [float(v) for v in self.offset_sigma_ut],
        }


def _shift(n, s1, s2, s3, s4, delta):
    """Moments of y + delta from the moments of y (exact binomial expansion)."""
    d = np.asarray(delta, dtype=np.float64)
    dd = float(d @ d)
    q = float(np.trace(s2))  # Σ|y|²
    s1d = float(s1 @ d)
    n1 = s1 + n * d
    n2 = s2 + np.outer(s1, d) + np.outer(d, s1) + n * np.outer(d, d)
    # Σ(y+d)|y+d|² with |y+d|² = |y|² + 2 d·y + |d|²
    n3 = s3 + 2.0 * (s2 @ d) + dd * s1 + d * q + 2.0 * d * s1d + n * dd * d
    n4 = (
        s4
        + 4.0 * float(d @ s2 @ d)
        + n * dd * dd
        + 4.0 * float(d @ s3)
        + 2.0 * dd * q
        + 4.0 * dd * s1d
    )
    return n1, n2, n3, n4


class SphereAccumulator:
    """Running sums for the algebraic sphere fit; see the module docstring."""

    def __init__(self, reference_ut=None):
        self.reference_ut = None if reference_ut is None else self._vec(reference_ut)
        self.n = 0
        self._s1 = np.zeros(3)
        self._s2 = np.zeros((3, 3))
        self._s3 = np.zeros(3)
        self._s4 = 0.0

    @staticmethod
    def _vec(v) -> np.ndarray:
        a = np.asarray(v, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"sample must be finite, got {a.tolist()}")
        return a.copy()

    # -- accumulation ----------------------------------------------------------------------
    def add(self, m_ut) -> None:
        """Add one (3,) sample in µT. O(1)."""
        m = self._vec(m_ut)
        if self.reference_ut is None:
            self.reference_ut = m.copy()
        y = m - self.reference_ut
        r2 = float(y @ y)
        self.n += 1
        self._s1 += y
        self._s2 += np.outer(y, y)
        self._s3 += y * r2
        self._s4 += r2 * r2

    def add_batch(self, m_ut) -> None:
        """Add (n, 3) samples in µT, vectorised."""
        m = np.asarray(m_ut, dtype=np.float64)
        if m.size == 0:
            return
        m = m.reshape(-1, 3)
        if not np.all(np.isfinite(m)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(m), axis=1))[0])
            raise ValueError(f"samples must be finite; row {bad} is {m[bad].tolist()}")
        if self.reference_ut is None:
            self.reference_ut = m[0].copy()
        y = m - self.reference_ut
        r2 = np.einsum("ij,ij->i", y, y)
        self.n += len(y)
        self._s1 += y.sum(axis=0)
        self._s2 += y.T @ y
        self._s3 += y.T @ r2
        self._s4 += float(r2 @ r2)

    def merge(self, other: "SphereAccumulator") -> "SphereAccumulator":
        """A new accumulator holding self ∪ other, about self's reference (other's if self is
        empty). Neither input is changed."""
        ref = self.reference_ut if self.reference_ut is not None else other.reference_ut
        out = SphereAccumulator(ref)
        for acc in (self, other):
            if acc.n == 0:
                continue
            s1, s2, s3, s4 = _shift(
                acc.n, acc._s1, acc._s2, acc._s3, acc._s4, acc.reference_ut - out.reference_ut
            )
            out.n += acc.n
            out._s1 += s1
            out._s2 += s2
            out._s3 += s3
            out._s4 += s4
        return out

    def copy(self) -> "SphereAccumulator":
        return SphereAccumulator.from_state(self.to_state())

    # -- solving ---------------------------------------------------------------------------
    def solve(
        self, min_samples: int = DEFAULT_MIN_SAMPLES, max_condition: float = DEFAULT_MAX_CONDITION
    ) -> SphereFit | FitFailure:
        """Offset and radius from the sums, or a FitFailure saying why not.

        ``max_condition`` bounds the condition number of the centred, isotropically scaled
        normal matrix; a yaw-only (flat) recording leaves the axis normal to its plane
        undetermined and fails here with ``ill_conditioned``.
        """
        if self.n < max(min_samples, 4):
            return FitFailure(
                "too_few_samples", f"{self.n} samples; the sphere fit needs at least {max(min_samples, 4)}"
            )
        n = self.n
        mu = self._s1 / n
        # moments about the sample mean (z = y − mu)
        z1, z2, z3, z4 = _shift(n, self._s1, self._s2, self._s3, self._s4, -mu)
        cov = z2 / n
        scale2 = float(np.trace(cov)) / 3.0
        if not np.isfinite(scale2) or scale2 <= 0:
            return FitFailure("ill_conditioned", "all samples are at one point: no coverage at all")
        s = np.sqrt(scale2)
        # scaled variables w = z / s; normal matrix of the design [2w, 1] divided by n
        w2 = z2 / (n * scale2)
        w1 = z1 / (n * s)  # ≈ 0 (rounding only)
        N = np.empty((4, 4))
        N[:3, :3] = 4.0 * w2
        N[:3, 3] = 2.0 * w1
        N[3, :3] = 2.0 * w1
        N[3, 3] = 1.0
        rhs = np.empty(4)
        rhs[:3] = 2.0 * z3 / (n * s**3)
        rhs[3] = float(np.trace(z2)) / (n * scale2)
        eig = np.linalg.eigvalsh(0.5 * (N + N.T))
        condition = float(eig[-1] / eig[0]) if eig[0] > 0 else float("inf")
        if not np.isfinite(condition) or condition > max_condition:
            return FitFailure(
                "ill_conditioned",
                f"coverage too thin: normal-matrix condition {condition:.3g} exceeds {max_condition:.3g}"
                " (the samples span too few directions, e.g. flat turns only)",
            )
        x = np.linalg.solve(N, rhs)
        c_w, d_w = x[:3], float(x[3])
        r2_w = d_w + float(c_w @ c_w)
        if not np.isfinite(r2_w) or r2_w <= 0:
            return FitFailure("degenerate", "the samples describe no sphere (squared radius ≤ 0)")
        offset = self.reference_ut + mu + s * c_w
        radius = s * np.sqrt(r2_w)
        # residual sum of squares of the scaled algebraic residual, back to µT²
        ssr_w = z4 / (n * scale2**2) - 2.0 * float(x @ rhs) + float(x @ N @ x)
        ssr_w = max(ssr_w, 0.0) * n
        rms_alg = np.sqrt(ssr_w / n) * scale2
        spread = np.sqrt(3.0) * s  # RMS distance of the samples from their mean
        if spread < CLOUD_MAX_SPREAD_UT and rms_alg / (2.0 * radius) > MAX_RMS_OVER_SPREAD * spread:
            return FitFailure(
                "degenerate",
                f"residual RMS {rms_alg / (2.0 * radius):.3g} µT is not small against the samples' spread"
                f" {spread:.3g} µT: a cloud, not a sphere (board held still?)",
            )
        dof = max(n - 4, 1)
        cov_x = (ssr_w / dof) * np.linalg.inv(N) / n
        offset_sigma = s * np.sqrt(np.clip(np.diag(cov_x)[:3], 0.0, None))
        return SphereFit(
            offset_ut=offset,
            field_ut=float(radius),
            condition=condition,
            n=n,
            rms_algebraic_ut2=float(rms_alg),
            offset_sigma_ut=offset_sigma,
        )

    # -- persistence -----------------------------------------------------------------------
    def to_state(self) -> dict:
        """JSON-able state; ``from_state(json.loads(json.dumps(s)))`` restores it bit-exactly
        (Python floats round-trip through JSON's shortest repr)."""
        return {
            "kind": _STATE_KIND,
            "version": _STATE_VERSION,
            "n": int(self.n),
            "reference_ut": None if self.reference_ut is None else [float(v) for v in self.reference_ut],
            "s1": [float(v) for v in self._s1],
            "s2": [[float(v) for v in row] for row in self._s2],
            "s3": [float(v) for v in self._s3],
            "s4": float(self._s4),
        }

    @classmethod
    def from_state(cls, d: dict) -> "SphereAccumulator":
        check_state(d, _STATE_KIND, _STATE_VERSION, "sphere-accumulator")
        try:
            acc = cls(d["reference_ut"])
            acc.n = int(d["n"])
            acc._s1 = np.asarray(d["s1"], dtype=np.float64).reshape(3).copy()
            acc._s2 = np.asarray(d["s2"], dtype=np.float64).reshape(3, 3).copy()
            acc._s3 = np.asarray(d["s3"], dtype=np.float64).reshape(3).copy()
            acc._s4 = float(d["s4"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"sphere-accumulator state is malformed: {exc}") from None
        if acc.n < 0 or (acc.n > 0 and acc.reference_ut is None):
            raise ValueError("sphere-accumulator state is inconsistent (n < 0 or missing reference)")
        return acc

    def __repr__(self) -> str:
        return f"SphereAccumulator(n={self.n}, reference_ut={None if self.reference_ut is None else self.reference_ut.tolist()})"
