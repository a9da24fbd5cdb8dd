"""The sensor model: one value that the simulator draws from and diagnosis fits.

Per sample i at time t_i, true unit field direction u_i (body frame) and channels x_i::

    r_i = (field_ut + f(t_i) + d(t_i)) · (1 + γ (T_i − T_ref))
          + Σ_j c_j Y_j(u_i)                                         radial: field wander,
                                                                     disturbances, gain, nonlinearity
    c_i = W⁻¹ (r_i u_i) + b + Σ_c K_c (x_ci − ref_c)                 the calibration, inverted
          + w(t_i) + s_i diag(σ) z_i                                 wander, noise: the conversion
    m_i = c_j(i) + g_i                                               the read: repeats, glitches
                                                                     (random, or a pulse train)
    m_i → clipped at ±saturation_ut (then flagged), rounded to quantum_ut per axis

W, b, field, K_c and ref_c are a :class:`~magcal.calibration.Calibration` (the deterministic
part, shared with every fit); γ the temperature gain; Y_j the degree-3/4 direction basis
(``magcal.sim.directions``); w and f the offset and field wander, sums of stationary Gaussian
components (``magcal.sim.wander``); d intermittent disturbances of the field's magnitude
(``magcal.sim.disturbance``); g_i rare one-sample glitches of a size in ``glitch_ut`` — in a
random direction, along one sensor axis (a corrupted register) or along the field (the read's
magnitude wrong for one read: W⁻¹u_i times the size, which moves |h| by exactly that) — at
random reads or, with ``glitch_period_s``, at the reads a nearly periodic train of pulses hits
(a source that fires on its own clock: a radio burst, a LED, another device on the bus) — pulse
j at φ + j·P + jitter·z_j, each kept with the probability that gives ``glitch_rate``;
z_i standard normal, s_i the read's noise level (1, or log-normal with E[s²] = 1 under a
heavy-tailed noise law, ``magcal.sim.noise_law``, which also gives the wander its
excursions). Repeated reads: a host that reads faster than the sensor converts (the
data-ready flag not awaited) gets the last conversion again, bit for bit; a share
``repeat_share`` of reads does, in the steady pattern of two unequal rates (read i shows
conversion ⌊i·(1 − share) + φ⌋, φ a random phase; j(i) the first read of that conversion). A
glitch corrupts one read, repeated or not. A recording of takes (``takes``, ``magcal.sim.takes``):
the recorder paused while the board was placed anew, and each placement sits in its own
hard-iron surroundings — a level of the field's magnitude per take (drawn N(0, level_sd_ut²)),
which every refit of such a recording removes, as it removes the calibration.

The value serialises to a plain dict (YAML or JSON) with units in its keys and a schema
version; ``from_dict`` refuses a malformed or unknown one with a message naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np

from ..core.calibration import Calibration
from . import directions
from . import wander as wander_mod
from .disturbance import Disturbances
from .noise_law import NoiseLaw
from .takes import Takes
from .wander import WanderComponent

SCHEMA = "magcal.sensor-model/9"
# /1: two glitch sizes (log-uniform), read the same; /2: no repeated reads (reads.repeat_share 0);
# /3: glitches at random reads only (no glitches.period_s); /4: no glitches along the field
# (glitches.radial_share 0); /5: white noise (no noise_lag1); /6: disturbances drawn log-uniform
# in size and duration apart (no disturbances.events); /7: one take (no takes); /8: Gaussian noise
# (no noise_law)
READS = ("magcal.sensor-model/1", "magcal.sensor-model/2", "magcal.sensor-model/3", "magcal.sensor-model/4",
         "magcal.sensor-model/5", "magcal.sensor-model/6", "magcal.sensor-model/7", "magcal.sensor-model/8", SCHEMA)
TEMP = "temp_c"


@dataclass(frozen=True)
class Draws:
    """The random parts of one simulated stream, (n, 3) each: standard-normal noise, glitch
    vectors in µT (zero where no glitch), offset wander in µT."""

    noise: np.ndarray
    glitch_ut: np.ndarray
    wander_ut: np.ndarray
    field_wander_ut: np.ndarray | None = None  # (n,): the field magnitude's wander
    shown: np.ndarray | None = None  # (n,) int: the read whose conversion each read shows (repeats)
    glitch_along_ut: np.ndarray | None = None  # (n,): glitches along the field, signed µT of |h|


@dataclass(frozen=True, eq=False)
class SensorModel:
    calibration: Calibration
    noise_ut: tuple = (0.4, 0.4, 0.4)
    noise_lag1: float = 0.0  # correlation of the noise between successive reads (|·| < 0.5; 0: white)
    noise_law: NoiseLaw = NoiseLaw()  # the white noise's and the wander's tails (Gaussian by default)
    quantum_ut: tuple = (0.0, 0.0, 0.0)  # 0: a continuous reading
    wander: tuple = ()
    glitch_rate: float = 0.0  # probability per sample
    glitch_ut: tuple = (4.0, 15.0)  # size quantiles at evenly spaced probabilities (two: log-uniform)
    glitch_axis_share: float = 0.0  # share of glitches along one sensor axis (else any direction)
    glitch_radial_share: float = 0.0  # share of glitches along the field (its magnitude read wrong)
    glitch_period_s: float | None = None  # glitches from a nearly periodic train of pulses (None: at random)
    glitch_jitter_s: float = 0.0  # each pulse's time off the train's grid, standard deviation
    disturbances: Disturbances | None = None  # intermittent departures of the field's magnitude
    nonlinearity_ut: tuple = (0.0,) * len(directions.NAMES)
    temp_gain_per_c: float = 0.0
    temp_ref_c: float = 25.0
    saturation_ut: float | None = None
    repeat_share: float = 0.0  # share of reads that repeat the previous conversion
    takes: Takes | None = None  # a recording of takes: each placement at its own level (None: one take)
    rate_hz: float = 50.0
    source: Mapping = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "noise_ut", _triple(self.noise_ut, "noise_ut", lo=0.0))
        object.__setattr__(self, "quantum_ut", _triple(self.quantum_ut, "quantum_ut", lo=0.0))
        object.__setattr__(self, "wander", tuple(self.wander))
        if not isinstance(self.noise_law, NoiseLaw):
            raise ValueError("noise_law must be a NoiseLaw")
        nl = tuple(float(v) for v in np.asarray(self.nonlinearity_ut, dtype=np.float64).reshape(-1))
        if len(nl) != len(directions.NAMES) or not np.all(np.isfinite(nl)):
            raise ValueError(f"nonlinearity_ut needs {len(directions.NAMES)} finite numbers")
        object.__setattr__(self, "nonlinearity_ut", nl)
        sizes = tuple(float(v) for v in np.asarray(self.glitch_ut, dtype=np.float64).reshape(-1))
        ordered = len(sizes) >= 2 and sizes[0] >= 0 and all(a <= b for a, b in zip(sizes, sizes[1:]))
        shares = (self.glitch_axis_share, self.glitch_radial_share)
        if not (0 <= self.glitch_rate < 1) or not ordered or not (min(shares) >= 0 and sum(shares) <= 1):
            raise ValueError("glitch rate must be in [0, 1), axis and radial shares ≥ 0 with a sum ≤ 1; glitch sizes "
                             "≥ 2 quantiles, 0 ≤ each ≤ the next")
        object.__setattr__(self, "glitch_ut", sizes)
        if not 0 <= self.repeat_share < 1:
            raise ValueError("repeat_share must be in [0, 1)")
        if not abs(self.noise_lag1) < 0.5:
            raise ValueError("noise_lag1 must lie in (-0.5, 0.5): the lag-1 correlation of a one-step moving average")
        period = self.glitch_period_s
        if period is not None and not (np.isfinite(period) and period > 0 and 0 <= self.glitch_jitter_s <= period):
            raise ValueError("glitch period_s must be positive (or absent), jitter_s in [0, period_s]")
        if period is None and self.glitch_jitter_s != 0:
            raise ValueError("glitch jitter_s needs a period_s")
        if self.saturation_ut is not None and not self.saturation_ut > 0:
            raise ValueError("saturation_ut must be positive (or absent)")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError("rate_hz must be positive")

    # -- the forward model ---------------------------------------------------------------
    def radius_ut(self, u: np.ndarray, channels: Mapping[str, np.ndarray] | None,
                  field_wander_ut: np.ndarray | None = None) -> np.ndarray:
        """|h| the sensor sees at directions ``u``: field (and its wander), temperature gain,
        nonlinearity."""
        r = np.full(len(u), self.calibration.field_ut)
        if field_wander_ut is not None:
            r = r + field_wander_ut
        if self.temp_gain_per_c and channels is not None and TEMP in channels:
            r = r * (1.0 + self.temp_gain_per_c * (np.asarray(channels[TEMP], np.float64) - self.temp_ref_c))
        if any(self.nonlinearity_ut):
            r = r + directions.radial_ut(u, self.nonlinearity_ut)
        return r

    def distort(self, u, channels: Mapping[str, np.ndarray] | None, draws: Draws) -> tuple[np.ndarray, np.ndarray]:
        """What the sensor reports for unit directions ``u`` (n, 3): (m (n, 3) µT, valid (n,))."""
        u = np.atleast_2d(np.asarray(u, dtype=np.float64))
        h = self.radius_ut(u, channels, draws.field_wander_ut)[:, None] * u
        m = self.calibration.distort(h, channels)
        m = m + draws.wander_ut + np.asarray(self.noise_ut) * draws.noise
        if draws.shown is not None:  # a repeated read shows the conversion before; a glitch corrupts one read
            m, u = m[draws.shown], u[draws.shown]
        m = m + draws.glitch_ut
        if draws.glitch_along_ut is not None:
            m = m + draws.glitch_along_ut[:, None] * self.along_field(u)
        valid = np.ones(len(m), bool)
        if self.saturation_ut is not None:
            valid = np.all(np.abs(m) < self.saturation_ut, axis=1)
            m = np.clip(m, -self.saturation_ut, self.saturation_ut)
        return quantize(m, self.quantum_ut), valid

    def draws(self, t_s, seed: int) -> Draws:
        """Fresh random parts for a stream at times ``t_s``, a function of ``seed`` alone."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x51D])
        noise = moving_average(rng.standard_normal((len(t), 3)) * self.noise_levels(seed, np.arange(len(t)))[:, None],
                               self.noise_lag1)
        if len(t) < 2 or np.all(t[1:] >= t[:-1]):  # already in time order (a recording's own times)
            path, field = wander_mod.draw_path(self.wander, rng, t)
        else:
            order = np.argsort(t, kind="stable")
            path, field = np.empty((len(t), 3)), np.empty(len(t))
            path[order], field[order] = wander_mod.draw_path(self.wander, rng, t[order])
        path, field = self.noise_law.wander(self.wander, path, field)
        if self.disturbances is not None:
            field = field + self.disturbances.draw(seed, t)
        if self.takes is not None:
            field = field + self.takes.levels(seed, t)
        g, along = self.glitch_vectors(rng, t, seed)
        return Draws(noise, g, path, field, repeated_reads(len(t), self.repeat_share, seed), along)

    def noise_levels(self, seed: int, k) -> np.ndarray:
        """(n,) the noise level of reads numbered ``k`` under the model's noise law (ones for
        Gaussian noise): a function of (seed, k) alone, so a board read at any sample agrees
        with a stream, and the other random parts do not move."""
        k = np.atleast_1d(np.asarray(k, dtype=np.int64))
        if self.noise_law.level_sd == 0.0:
            return np.ones(len(k))
        key = (int(seed) & 0xFFFFFFFF) * 4 + _LEVEL
        u1, u2 = np.maximum(hash_uniform(key, k), 1e-300), hash_uniform(key + 1, k)
        return self.noise_law.levels(np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2))

    def glitch_vectors(self, rng: np.random.Generator, t_s, seed: int, rate: float | None = None,
                       read_s: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """((n, 3) glitch vectors, (n,) glitches along the field or None) for reads at times
        ``t_s`` at ``rate`` (default: the model's), at random reads (``glitch_parts``) or at those
        the pulse train hits (``pulse_reads``: each read takes the pulses nearer to it than to
        the reads either side, or with ``read_s`` those within half of it). The draws consumed
        from ``rng`` depend on n alone, and a higher rate keeps the glitches a lower one had."""
        rate = self.glitch_rate if rate is None else rate
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        shares = (self.glitch_axis_share, self.glitch_radial_share)
        if self.glitch_period_s is None:
            return glitch_parts(rng, len(t), rate, self.glitch_ut, *shares)
        every, along = glitch_parts(rng, len(t), 1.0, self.glitch_ut, *shares)  # a glitch for each read
        hit = pulse_reads(t, rate, self.glitch_period_s, self.glitch_jitter_s, read_s or 1.0 / self.rate_hz, seed,
                          stream=read_s is None)
        return every * hit[:, None], None if along is None else along * hit

    def along_field(self, u: np.ndarray) -> np.ndarray:
        """(n, 3) W⁻¹u: the change of the raw reading that moves |h| by one µT along the
        field direction ``u`` (a glitch along the field, per µT of its size)."""
        return np.linalg.solve(np.asarray(self.calibration.soft_iron, dtype=np.float64), np.atleast_2d(u).T).T

    def simulate(self, u, t_s, channels: Mapping[str, np.ndarray] | None, seed: int):
        """(m, valid) for directions ``u`` at times ``t_s``: the twin of a recording."""
        return self.distort(u, channels, self.draws(t_s, seed))

    def directions_of(self, m_ut, channels: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """The inverse model: unit field directions (n, 3) behind measurements ``m_ut``."""
        h = self.calibration.correct(m_ut, channels)
        return h / np.linalg.norm(h, axis=1, keepdims=True)

    def without(self, effect: str) -> "SensorModel":
        """This model with one effect removed (``wander``, ``field_wander``, ``nonlinearity``, ``glitches``,
        ``disturbances``, ``soft_iron``, ``temperature_gain``, ``saturation``, ``repeats``, ``takes``,
        ``quantum``, ``noise_law`` or a channel name)."""
        cal = self.calibration
        if effect in ("wander", "field_wander"):
            frame = wander_mod.OFFSET if effect == "wander" else wander_mod.FIELD
            return replace(self, wander=tuple(c for c in self.wander if c.frame != frame))
        if effect == "disturbances":
            return replace(self, disturbances=None)
        if effect == "nonlinearity":
            return replace(self, nonlinearity_ut=(0.0,) * len(directions.NAMES))
        if effect == "glitches":
            return replace(self, glitch_rate=0.0)
        if effect == "temperature_gain":
            return replace(self, temp_gain_per_c=0.0)
        if effect == "saturation":
            return replace(self, saturation_ut=None)
        if effect == "repeats":
            return replace(self, repeat_share=0.0)
        if effect == "takes":
            return replace(self, takes=None)
        if effect == "quantum":
            return replace(self, quantum_ut=(0.0, 0.0, 0.0))
        if effect == "noise_law":
            return replace(self, noise_law=NoiseLaw())
        if effect == "soft_iron":
            w = cal.soft_iron
            iso = np.eye(3) * float(np.cbrt(np.linalg.det(w)))
            return replace(self, calibration=replace_calibration(cal, soft_iron=iso))
        if effect in cal.coef_ut_per_unit:
            coef = {k: v for k, v in cal.coef_ut_per_unit.items() if k != effect}
            ref = {k: v for k, v in cal.reference.items() if k != effect}
            return replace(self, calibration=replace_calibration(cal, coef_ut_per_unit=coef, reference=ref))
        raise ValueError(f"the model has no effect {effect!r} to remove")

    def effects(self) -> tuple[str, ...]:
        """The effects this model carries beyond hard iron, field and Gaussian white noise."""
        out = []
        w = self.calibration.soft_iron
        if np.max(np.abs(w / np.cbrt(np.linalg.det(w)) - np.eye(3))) > 1e-9:
            out.append("soft_iron")
        out += list(self.calibration.coef_ut_per_unit)
        offset, field = wander_mod.split(self.wander)
        out += ["wander"] if offset else []
        out += ["field_wander"] if field else []
        out += ["nonlinearity"] if any(self.nonlinearity_ut) else []
        out += ["glitches"] if self.glitch_rate > 0 else []
        out += ["disturbances"] if self.disturbances is not None and self.disturbances.rate_per_s > 0 else []
        out += ["temperature_gain"] if self.temp_gain_per_c else []
        out += ["saturation"] if self.saturation_ut is not None else []
        out += ["repeats"] if self.repeat_share > 0 else []
        out += ["takes"] if self.takes is not None else []
        out += [] if self.noise_law.gaussian else ["noise_law"]
        return tuple(out)

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = {"schema": SCHEMA}
        d.update(self.calibration.to_dict())
        d.update({
            "noise_ut": list(self.noise_ut),
            "noise_lag1": float(self.noise_lag1),
            "noise_law": self.noise_law.to_dict(),
            "quantum_ut": list(self.quantum_ut),
            "wander": [c.to_dict() for c in self.wander],
            "glitches": {"rate_per_sample": float(self.glitch_rate), "size_ut": list(self.glitch_ut),
                         "axis_share": float(self.glitch_axis_share),
                         "radial_share": float(self.glitch_radial_share),
                         "period_s": None if self.glitch_period_s is None else float(self.glitch_period_s),
                         "jitter_s": float(self.glitch_jitter_s)},
            "disturbances": None if self.disturbances is None else self.disturbances.to_dict(),
            "nonlinearity_ut": {k: v for k, v in zip(directions.NAMES, self.nonlinearity_ut) if v},
            "temp_gain_per_c": float(self.temp_gain_per_c),
            "temp_ref_c": float(self.temp_ref_c),
            "saturation_ut": None if self.saturation_ut is None else float(self.saturation_ut),
            "reads": {"repeat_share": float(self.repeat_share)},
            "takes": None if self.takes is None else self.takes.to_dict(),
            "rate_hz": float(self.rate_hz),
        })
        if self.source:
            d["source"] = dict(self.source)
        return d

    @classmethod
    def from_dict(cls, d: Mapping) -> "SensorModel":
        """The model from ``to_dict``'s shape; ValueError naming the problem otherwise."""
        if not isinstance(d, Mapping):
            raise ValueError("a sensor model is a mapping of named values")
        if d.get("schema") not in READS:
            raise ValueError(f"unknown sensor model schema {d.get('schema')!r} (this version reads {', '.join(map(repr, READS))})")
        try:
            return cls(
                calibration=Calibration.from_dict(d),
                noise_ut=d.get("noise_ut", (0.0, 0.0, 0.0)),
                noise_lag1=float(d.get("noise_lag1", 0.0)),
                noise_law=NoiseLaw.from_dict(d.get("noise_law")),
                quantum_ut=d.get("quantum_ut", (0.0, 0.0, 0.0)),
                wander=tuple(WanderComponent.from_dict(c) for c in d.get("wander", ())),
                glitch_rate=float(d.get("glitches", {}).get("rate_per_sample", 0.0)),
                glitch_ut=tuple(d.get("glitches", {}).get("size_ut", (4.0, 15.0))),
                glitch_axis_share=float(d.get("glitches", {}).get("axis_share", 0.0)),
                glitch_radial_share=float(d.get("glitches", {}).get("radial_share", 0.0)),
                glitch_period_s=_optional(d.get("glitches", {}).get("period_s")),
                glitch_jitter_s=float(d.get("glitches", {}).get("jitter_s", 0.0)),
                disturbances=None if d.get("disturbances") is None else Disturbances.from_dict(d["disturbances"]),
                nonlinearity_ut=_nonlinearity(d.get("nonlinearity_ut", {})),
                temp_gain_per_c=float(d.get("temp_gain_per_c", 0.0)),
                temp_ref_c=float(d.get("temp_ref_c", 25.0)),
                saturation_ut=None if d.get("saturation_ut") is None else float(d["saturation_ut"]),
                repeat_share=float((d.get("reads") or {}).get("repeat_share", 0.0)),
                takes=None if d.get("takes") is None else Takes.from_dict(d["takes"]),
                rate_hz=float(d.get("rate_hz", 50.0)),
                source=dict(d.get("source", {})),
            )
        except KeyError as exc:
            raise ValueError(f"sensor model lacks {exc.args[0]!r}") from None
        except (TypeError, AttributeError) as exc:
            raise ValueError(f"sensor model is malformed: {exc}") from None


def replace_calibration(cal: Calibration, **changes) -> Calibration:
    d = {"offset_ut": cal.offset_ut, "field_ut": cal.field_ut, "soft_iron": cal.soft_iron,
         "coef_ut_per_unit": cal.coef_ut_per_unit, "reference": cal.reference}
    d.update(changes)
    return Calibration(**d)


def moving_average(w: np.ndarray, rho: float) -> np.ndarray:
    """Unit-variance noise whose successive reads correlate by ``rho`` (|rho| < 0.5), from white
    ``w`` (n, 3): (w_k + θ·w_{k−1}) / √(1 + θ²) with θ / (1 + θ²) = rho — a sensor that filters
    its conversions (rho > 0) or alternates its bridge between reads (rho < 0). rho 0 returns
    ``w`` itself."""
    if rho == 0 or len(w) < 2:
        return w
    out = w.copy()
    out[1:] = with_previous(w[1:], w[:-1], rho)
    return out


def with_previous(w: np.ndarray, w_before: np.ndarray, rho: float) -> np.ndarray:
    """(w + θ·w_before) / √(1 + θ²), θ / (1 + θ²) = rho: the moving average of white draws
    ``w`` and the draws of the reads before them."""
    if rho == 0:
        return w
    theta = (1.0 - np.sqrt(1.0 - 4.0 * rho * rho)) / (2.0 * rho)
    return (w + theta * w_before) / np.sqrt(1.0 + theta * theta)


def quantize(m: np.ndarray, quantum_ut) -> np.ndarray:
    q = np.asarray(quantum_ut, dtype=np.float64)
    if not np.any(q > 0):
        return m
    safe = np.where(q > 0, q, 1.0)
    return np.where(q > 0, np.round(np.round(m / safe) * safe, 9), m)


def first_reads(k, share: float, seed: int) -> np.ndarray:
    """For reads numbered ``k``, the first read of the conversion each shows when a share
    ``share`` of reads repeat the one before: read k shows conversion ⌊k·(1 − share) + φ⌋, the
    steady pattern of a host polling faster than the sensor converts (at 24 % repeats: every
    4th or 5th read), φ drawn from ``seed`` on a generator of its own (the other random parts
    do not move). A function of (seed, k) alone, so a board can be read at any sample."""
    k = np.asarray(k, dtype=np.int64)
    if share <= 0:
        return k
    phase = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EAD]).random()
    conv = np.floor(k * (1.0 - share) + phase)
    first = np.ceil((conv - phase) / (1.0 - share)).astype(np.int64)
    first = np.where(np.floor(first * (1.0 - share) + phase) < conv, first + 1, first)  # rounding
    return np.clip(first, 0, k)  # the first read of all shows a fresh conversion


def repeated_reads(n: int, share: float, seed: int) -> np.ndarray | None:
    """(n,) the read whose conversion each of ``n`` reads shows (``first_reads``), None when
    no read repeats."""
    return None if share <= 0 or n == 0 else first_reads(np.arange(n), share, seed)


def glitch_sizes(q: np.ndarray, size_ut: tuple) -> np.ndarray:
    """Sizes at probabilities ``q`` in [0, 1] of the distribution whose quantiles at evenly
    spaced probabilities are ``size_ut``, interpolated in the logarithm: two quantiles make it
    log-uniform between them (as many between 1 and 2 µT as between 2 and 4), more follow the
    shape a recording showed."""
    logs = np.log(np.maximum(np.asarray(size_ut, dtype=np.float64), 1e-9))
    return np.exp(np.interp(q, np.linspace(0.0, 1.0, len(logs)), logs))


def glitch_parts(rng: np.random.Generator, n: int, rate: float, size_ut: tuple, axis_share: float = 0.0,
                 radial_share: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """((n, 3) glitch vectors, (n,) glitches along the field or None): with probability
    ``rate`` a one-sample jump of a size drawn from the quantiles ``size_ut``
    (``glitch_sizes``) — along one sensor axis (either sign) with probability ``axis_share``
    (a corrupted register), along the field with probability ``radial_share`` (a signed size
    of |h|, which ``SensorModel.distort`` turns into a vector along the read's own field), else
    along a random direction; zero elsewhere. The draws consumed depend on n alone (and on
    whether the shares are zero), so a block of samples is reproducible whatever the rate."""
    out = np.zeros((n, 3))
    if rate <= 0 or n == 0:
        return out, None
    hit = rng.random(n) < rate
    d = rng.standard_normal((n, 3))
    mag = glitch_sizes(rng.random(n), size_ut)
    radial = np.zeros(n, bool)
    if axis_share > 0 or radial_share > 0:
        v = rng.random(n)
        along = v < axis_share
        radial = hit & (v >= axis_share) & (v < axis_share + radial_share)
        axis = rng.integers(0, 3, n)
        d[along] = np.eye(3)[axis[along]] * np.sign(d[along, 0])[:, None]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    keep = hit & ~radial
    out[keep] = d[keep] * mag[keep, None]
    return out, (np.where(radial, np.sign(d[:, 0]) * mag, 0.0) if radial_share > 0 else None)


def hash_uniform(seed: int, idx) -> np.ndarray:
    """A deterministic uniform(0, 1) per integer index (splitmix64): random numbers that are a
    function of (seed, index), for processes sampled at any time in any order."""
    with np.errstate(over="ignore"):
        x = np.asarray(idx, dtype=np.int64).astype(np.uint64) + np.uint64(int(seed) & 0xFFFFFFFFFFFFFFFF) * np.uint64(0x9E3779B97F4A7C15)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) / float(1 << 53)


_PULSE = 0x9F15E
_LEVEL = 0x1E7E1


def pulse_reads(t_s, rate: float, period_s: float, jitter_s: float, read_s: float, seed: int,
                stream: bool = False) -> np.ndarray:
    """(n,) bool: the reads at times ``t_s`` a nearly periodic train of pulses hits — pulse j at
    φ + j·period_s + jitter_s·z_j (φ uniform over a period, z_j standard normal, a pulse within
    half a period of its slot), kept with probability q = rate·period_s / read_s (a full train
    hits one read in period_s / read_s, ``read_s`` the mean read interval; q ≤ 1), hitting the
    read within half a read interval of it — or, for a ``stream`` (irregular times), the read
    it lies nearest to. A function of (seed, t): each pulse's jitter and whether it is kept
    come from its index, so a board read at any time agrees with a stream, and a higher rate
    keeps the pulses a lower one kept."""
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    hit = np.zeros(len(t), bool)
    if rate <= 0 or not len(t):
        return hit
    lo, hi = t - 0.5 * read_s, t + 0.5 * read_s
    if stream and len(t) > 1:  # each read's share of time: halfway to the reads either side
        o = np.argsort(t, kind="stable")
        mid = 0.5 * (t[o][1:] + t[o][:-1])
        lo[o[1:]], hi[o[:-1]] = mid, mid
    key = (int(seed) & 0xFFFFFFFF) * 4 + _PULSE
    phase = float(hash_uniform(key, -1)) * period_s
    q = min(rate * period_s / read_s, 1.0)
    j0 = np.round((t - phase) / period_s).astype(np.int64)
    for j in (j0 - 1, j0, j0 + 1):  # the jitter is at most a period: a pulse lands near its own slot
        u1, u2 = np.maximum(hash_uniform(key + 1, j), 1e-300), hash_uniform(key + 2, j)
        z = np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)
        bound = 0.5 * period_s / max(jitter_s, 1e-300)  # off its slot by at most half a period
        at = phase + j * period_s + jitter_s * np.clip(z, -bound, bound)
        hit |= (hash_uniform(key + 3, j) < q) & (at >= lo) & (at < hi)
    return hit


def _optional(v) -> float | None:
    return None if v is None else float(v)


def _triple(v, name: str, lo: float) -> tuple:
    a = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,))
    if not np.all(np.isfinite(a)) or np.any(a < lo):
        raise ValueError(f"{name} must be three finite numbers ≥ {lo}, got {list(a)}")
    return tuple(float(x) for x in a)


def _nonlinearity(d) -> tuple:
    if not isinstance(d, Mapping):
        raise ValueError("nonlinearity_ut maps a direction term (y3_m3 … y4_p4) to µT")
    unknown = set(d) - set(directions.NAMES)
    if unknown:
        raise ValueError(f"nonlinearity_ut has unknown terms {sorted(unknown)} (known: {', '.join(directions.NAMES)})")
    return tuple(float(d.get(k, 0.0)) for k in directions.NAMES)
