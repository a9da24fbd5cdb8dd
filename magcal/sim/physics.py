"""The simulated board: an MPU-9150's magnetometer (AK8975) being waved around.

Everything that simulates the sensor — the ``sim://`` board, the emulated Arduino's TWI bus,
the fake I2C bus, the tests and the benchmarks — draws its numbers from here, and the sensor
itself is one :class:`~magcal.sim.model.SensorModel` (the value diagnosis fits): this module
adds the motion, the environment (temperature, current) and the chip's registers.

Model, per measurement k at time t (sensor frame, µT)::

    h(t)  = R(t)ᵀ h_world                        Earth field seen by the body
    m_k   = SensorModel(h(t)/|h|, channels(t))   A h + b + β (T − T_ref) + κ I + d·t + w(t) + g_k + n_k
    raw_k = clamp(round(m_k / (q · gain)))        gain = (ASA + 128)/256 per axis
    st2_k = HOFL when Σ|m_k| ≥ the chip's overflow sum (2400 µT AK8975, 4912 µT AK8963/AK09916)

q and the clamp are the chip's (``Physics.chip``, a row of :mod:`magcal.core.chips`: 0.3 µT and
±4095 for the MPU-9150's AK8975, the default; 0.6/0.15 µT for the AK8963; 0.15 µT for the AK09916).

A is the soft-iron/scale distortion (``distortion``, symmetric: a rotation cannot be told from
magnitudes), b hard iron, β temperature coefficient, κ current coefficient, d slow drift, w the
offset wander, g_k glitches (rare jumps), n_k white noise. ``Scenario(model=…)`` replaces the
sensor part with any SensorModel (one fitted to a real recording, say).

Determinism: every quantity is a function of (seed, t) or (seed, k) only, so a stream can be
sampled at any time (the emulator asks at its own simulated times) and reproduced exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from ..core.calibration import Calibration
from ..core.chips import MPU9150, NEUTRAL_ASA, Chip
from ..core.sample import ST2_HOFL, asa_gain, temp_c_to_raw
from ..core.series import Series
from . import wander as wander_mod
from .model import Draws, SensorModel, first_reads, glitch_parts, hash_uniform, pulse_reads, with_previous

HOFL_SUM_UT = MPU9150.overflow_sum_ut  # the default chip's (AK8975) overflow sum
_BLOCK = 1024  # noise is drawn in blocks of this many measurements, keyed by (seed, block)


@dataclass(frozen=True)
class Motion:
    """How the board is moved: ``sphere`` (hand-waving over all directions), ``tilt`` (level
    within ±max_tilt_deg, yaw free), ``yaw`` (flat turns), ``still``."""

    kind: str = "sphere"
    max_tilt_deg: float = 30.0
    period_s: float = 25.0

    def __post_init__(self):
        if self.kind not in ("sphere", "tilt", "yaw", "still"):
            raise ValueError(f"unknown motion kind {self.kind!r} (sphere, tilt, yaw, still)")


@dataclass(frozen=True)
class Temperature:
    """Die temperature: ``base_c`` plus a non-monotone swing of ``swing_c`` peak-to-peak
    (a warm-up and a slower oscillation), so temperature is not a proxy for time."""

    base_c: float = 25.0
    swing_c: float = 0.0
    period_s: float = 90.0


@dataclass(frozen=True)
class Current:
    """An intermittent current channel (motor, heater): ``level_a`` when on, 0 when off, a
    duty cycle ``duty`` over on/off segments of random length around ``segment_s``."""

    level_a: float = 0.0
    duty: float = 0.4
    segment_s: float = 4.0


@dataclass(frozen=True)
class Physics:
    field_ut: float = 50.0
    dip_deg: float = 60.0
    hard_iron_ut: tuple = (0.0, 0.0, 0.0)
    distortion: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    noise_ut: float = 0.4
    accel_noise_g: float = 0.003  # the accelerometer's white noise, per axis (an MPU's ±2 g range at ~40 Hz bandwidth)
    asa: tuple = (176, 178, 166)
    quantize: bool = True
    temp_coef_ut_per_c: tuple = (0.0, 0.0, 0.0)
    temp_ref_c: float = 25.0
    current_coef_ut_per_a: tuple = (0.0, 0.0, 0.0)
    drift_ut_per_s: tuple = (0.0, 0.0, 0.0)
    glitch_rate: float = 0.0
    glitch_ut: tuple = (4.0, 15.0)
    wander: tuple = ()  # magcal.sim.wander.WanderComponent components of the offset
    # what the internal self-test coil reads, in ASA-adjusted counts of this chip (None: the
    # chip's typical healthy reading, inside its datasheet window; a dead coil reads about 0)
    self_test_counts: tuple | None = None
    chip: Chip = MPU9150  # whose quantum, range, overflow and self-test the registers follow

    def __post_init__(self):
        if not self.chip.has_asa and tuple(self.asa) != NEUTRAL_ASA:  # no fuse ROM: factor 1
            object.__setattr__(self, "asa", NEUTRAL_ASA)
        if self.self_test_counts is None:
            object.__setattr__(self, "self_test_counts", self.chip.self_test_typical)

    @property
    def lsb_ut(self) -> np.ndarray:
        """µT per count per axis: the chip's quantum times its sensitivity adjustment."""
        return self.chip.ut_per_count * np.array([asa_gain(a) for a in self.asa])

    def self_test_raw(self) -> tuple[int, int, int]:
        """The data registers in self-test mode: the adjusted reading undone by this chip's
        ASA (sensitivity adjustment: adjusted = raw · (ASA + 128) / 256), truncated as the
        register holds it."""
        lo, hi = self.chip.count_min, self.chip.count_max
        return tuple(int(max(lo, min(hi, int(c * 256 / (a + 128))))) for c, a in zip(self.self_test_counts, self.asa))

    def truth(self) -> Calibration:
        """The calibration that exactly inverts this physics (at T_ref, I = 0, t = 0)."""
        a = np.asarray(self.distortion, dtype=np.float64)
        coef = {}
        if np.any(self.temp_coef_ut_per_c):
            coef["temp_c"] = self.temp_coef_ut_per_c
        if np.any(self.current_coef_ut_per_a):
            coef["current_a"] = self.current_coef_ut_per_a
        if np.any(self.drift_ut_per_s):
            coef["t_s"] = self.drift_ut_per_s
        ref = {"temp_c": self.temp_ref_c} if "temp_c" in coef else {}
        return Calibration(
            offset_ut=self.hard_iron_ut,
            field_ut=self.field_ut,
            soft_iron=np.linalg.inv(a),
            coef_ut_per_unit=coef,
            reference=ref,
        )

    def sensor_model(self) -> SensorModel:
        """This board's sensor as the one model (quantisation is the chip's, in to_counts)."""
        a = np.asarray(self.distortion, dtype=np.float64)
        if not np.allclose(a, a.T, atol=1e-12):
            raise ValueError("distortion must be symmetric: a rotation of the sensor is not part of the magnitude model")
        return SensorModel(calibration=self.truth(), noise_ut=(self.noise_ut,) * 3, wander=self.wander,
                           glitch_rate=self.glitch_rate, glitch_ut=self.glitch_ut)


def _rot(axis: int, ang: np.ndarray) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    n = len(ang)
    r = np.zeros((n, 3, 3))
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    r[:, axis, axis] = 1.0
    r[:, i, i] = c
    r[:, j, j] = c
    sign = -1.0 if axis == 1 else 1.0
    r[:, i, j] = -s * sign
    r[:, j, i] = s * sign
    return r


@dataclass(frozen=True)
class Scenario:
    """Physics + motion + environment + seed: a reproducible stream of measurements."""

    physics: Physics = field(default_factory=Physics)
    motion: Motion = field(default_factory=Motion)
    temperature: Temperature = field(default_factory=Temperature)
    current: Current = field(default_factory=Current)
    seed: int = 0
    model: SensorModel | None = None  # the sensor; None: the one ``physics`` describes

    @property
    def sensor(self) -> SensorModel:
        return self.model if self.model is not None else _sensor_of(self.physics)

    # -- deterministic functions of time --------------------------------------------------
    @property
    def _phases(self) -> np.ndarray:
        return _phases(self.seed)

    def orientation(self, t_s) -> np.ndarray:
        """Body-to-world rotations R(t), (n, 3, 3): smooth, hand-waving-like."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        p = self._phases
        base = self.motion.period_s
        w = 2 * np.pi / (base * p[0:4])  # four incommensurate rates
        wobble = 0.15 * np.sin(w[3] * 3.1 * t + p[8])
        yaw = w[0] * t + p[4] + wobble
        kind = self.motion.kind
        if kind == "sphere":
            pitch = np.arcsin(np.clip(0.98 * np.sin(w[1] * t + p[5]) + 0.02 * np.sin(w[3] * t), -1, 1))
            roll = np.pi * np.sin(w[2] * t + p[6])
        elif kind == "tilt":
            m = np.deg2rad(self.motion.max_tilt_deg)
            pitch = m * np.sin(w[1] * t + p[5])
            roll = m * np.sin(w[2] * t + p[6])
        elif kind == "yaw":
            pitch = np.deg2rad(2.0) * np.sin(w[1] * t + p[5])
            roll = np.deg2rad(2.0) * np.sin(w[2] * t + p[6])
        else:  # still
            yaw = np.full_like(t, p[4])
            pitch = np.full_like(t, 0.3 * (p[5] - np.pi))
            roll = np.full_like(t, 0.3 * (p[6] - np.pi))
        return _rot(2, yaw) @ _rot(1, pitch) @ _rot(0, roll)

    def earth_body_ut(self, t_s) -> np.ndarray:
        """The Earth field as the body sees it, (n, 3) µT."""
        dip = np.deg2rad(self.physics.dip_deg)
        hw = self.physics.field_ut * np.array([np.cos(dip), 0.0, np.sin(dip)])
        r = self.orientation(t_s)
        return np.einsum("nji,j->ni", r, hw)

    def accel_body_g(self, t_s, k) -> np.ndarray:
        """What the accelerometer of reads ``k`` at ``t_s`` shows, (n, 3) g: the reaction to
        gravity, Rᵀ·(0, 0, 1) — +1 g on the body axis that points up — plus white noise. The
        hand's own accelerations are left out (the waving is slow), so the reading says which way
        is up, which is all the guidance needs of it. It is in the body axes, which are the
        magnetometer's; a real IMU's accelerometer has its own (``Chip.mag_from_accel``), which
        the simulated boards turn it into before sending (``magcal.devices.simboard.accel_counts``)."""
        r = self.orientation(t_s)
        noise = _accel_noise(self.seed, np.asarray(k, dtype=np.int64))
        return r[:, 2, :] + self.physics.accel_noise_g * noise

    def temp_c(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        tp = self.temperature
        if tp.swing_c == 0:
            return np.full_like(t, tp.base_c)
        p = self._phases
        warm = 1.0 - np.exp(-t / (0.4 * tp.period_s))
        osc = np.sin(2 * np.pi * t / tp.period_s + p[7])
        shape = 0.55 * warm + 0.45 * osc  # in about [-0.45, 1]: non-monotone
        return tp.base_c + tp.swing_c * (shape - 0.275) / 1.45 * 1.0

    def current_a(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        cur = self.current
        if cur.level_a == 0:
            return np.zeros_like(t)
        seg = np.floor(t / cur.segment_s).astype(np.int64)
        on = hash_uniform(self.seed + 7919, seg) < cur.duty
        ramp = np.clip((t - seg * cur.segment_s) / 0.2, 0, 1)  # 0.2 s spin-up
        return np.where(on, cur.level_a * ramp, 0.0)

    # -- per-measurement randomness -------------------------------------------------------
    def _noise_glitch(self, k: np.ndarray, sensor: SensorModel):
        """(noise, each read at its level under the noise law; glitch vectors; glitches along the
        field) of reads ``k``; a model whose glitches come from a pulse train gets a glitch for
        every read, which ``field_ut`` keeps where the train hits."""
        k = np.asarray(k, dtype=np.int64)
        blocks = np.unique(k // _BLOCK)
        noise = np.empty((len(k), 3))
        glitch = np.zeros((len(k), 3))
        along = np.zeros(len(k))
        rate = sensor.glitch_rate if sensor.glitch_period_s is None else 1.0
        for b in blocks:
            nb, gb, ab = _block(self.seed, int(b), rate, tuple(sensor.glitch_ut), sensor.glitch_axis_share,
                                sensor.glitch_radial_share)
            sel = (k // _BLOCK) == b
            noise[sel] = nb[k[sel] % _BLOCK]
            glitch[sel] = gb[k[sel] % _BLOCK]
            along[sel] = ab[k[sel] % _BLOCK]
        return noise * sensor.noise_levels(self.seed, k)[:, None], glitch, along

    # -- measurements ------------------------------------------------------------------------
    def channels(self, t_s) -> dict[str, np.ndarray]:
        """The environment at times ``t_s``: die temperature, current, time."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        return {"temp_c": self.temp_c(t), "current_a": self.current_a(t), "t_s": t}

    def field_ut(self, t_s, k) -> tuple[np.ndarray, np.ndarray]:
        """The sensor's reading before the chip quantises it, (n, 3) µT, and the glitch
        vectors: the sensor model driven by this motion and environment."""
        sensor = self.sensor
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        k = np.atleast_1d(np.asarray(k, dtype=np.int64))
        noise, glitch, along = self._noise_glitch(k, sensor)
        if sensor.glitch_period_s is not None:  # the reads the train hits, at their own times
            hit = pulse_reads(t, sensor.glitch_rate, sensor.glitch_period_s, sensor.glitch_jitter_s,
                              _read_interval(t, k, sensor.rate_hz), self.seed)
            glitch, along = glitch * hit[:, None], along * hit
        if sensor.repeat_share > 0:  # a repeated read shows an earlier conversion, its time and noise
            first = first_reads(k, sensor.repeat_share, self.seed)
            o = np.argsort(k, kind="stable")  # the time of a read asked for is taken as it is (bit for bit)
            back = t - (k - first) * _read_interval(t, k, sensor.rate_hz)
            t = np.where(np.isin(first, k), np.interp(first, k[o], t[o]), back)
            noise = self._noise_glitch(first, sensor)[0]
        if sensor.noise_lag1:  # noise correlated with the read before's (a read 0 has none before it)
            own = first if sensor.repeat_share > 0 else k
            noise = np.where((own > 0)[:, None], with_previous(noise, self._noise_glitch(np.maximum(own - 1, 0), sensor)[0],
                                                               sensor.noise_lag1), noise)
        h = self.earth_body_ut(t)
        u = h / np.linalg.norm(h, axis=1, keepdims=True)
        offset, field = sensor.noise_law.wander(sensor.wander, *wander_mod.draw(sensor.wander, self.seed, t))
        if sensor.disturbances is not None:
            field = field + sensor.disturbances.draw(self.seed, t)
        draws = Draws(noise=noise, glitch_ut=glitch, wander_ut=offset, field_wander_ut=field, glitch_along_ut=along)
        m, _ = sensor.distort(u, self.channels(t), draws)
        return m, glitch + along[:, None] * sensor.along_field(u)

    def measure(self, t_s, k) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the chip reports: raw counts (n, 3) int, ST2 (n,), TEMP_OUT raw (n,)."""
        m, _ = self.field_ut(t_s, k)
        return self.to_counts(m) + (np.array([temp_c_to_raw(x, self.physics.chip) for x in self.temp_c(t_s)]),)

    def to_counts(self, m_ut: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ph = self.physics
        x = m_ut / ph.lsb_ut
        raw = np.round(x) if ph.quantize else x
        hofl = np.abs(m_ut).sum(axis=1) >= ph.chip.overflow_sum_ut
        raw = np.clip(raw, ph.chip.count_min, ph.chip.count_max)
        st2 = np.where(hofl, ST2_HOFL, 0).astype(np.int64)
        return (raw.astype(np.int64) if ph.quantize else raw), st2

    def simulate(self, n: int, rate_hz: float = 50.0, t0_s: float = 0.0) -> "SimRun":
        """n measurements at ``rate_hz``: the recording and the truth behind it."""
        k = np.arange(n)
        t = t0_s + k / float(rate_hz)
        m, glitch = self.field_ut(t, k)
        raw, st2 = self.to_counts(m)
        measured = raw * self.physics.lsb_ut
        if self.model is not None:  # the modelled sensor's own reading (its quantum, its rails)
            measured = m
            if self.model.saturation_ut is not None:
                st2 = np.where(np.any(np.abs(m) >= self.model.saturation_ut, axis=1), ST2_HOFL, st2)
        channels = {}
        if self.temperature.swing_c or np.any(self.physics.temp_coef_ut_per_c):
            channels["temp_c"] = self.temp_c(t)
        if self.current.level_a:
            channels["current_a"] = self.current_a(t)
        valid = st2 == 0
        series = Series(t_s=t, field_ut=measured, channels=channels, valid=valid, seq=k % 65536)
        return SimRun(
            series=series,
            raw=raw,
            st2=st2,
            earth_ut=self.earth_body_ut(t),
            glitch_idx=np.flatnonzero(np.any(glitch != 0, axis=1)),
            truth=self.sensor.calibration,
        )

    def with_physics(self, **changes) -> "Scenario":
        return replace(self, physics=replace(self.physics, **changes))

    def on_chip(self, chip: Chip) -> "Scenario":
        """The same board carrying ``chip``: its quantum, range, overflow and healthy self-test."""
        return self.with_physics(chip=chip, self_test_counts=None)


@dataclass(frozen=True)
class SimRun:
    series: Series
    raw: np.ndarray
    st2: np.ndarray
    earth_ut: np.ndarray
    glitch_idx: np.ndarray
    truth: Calibration


def _sensor_of(physics: Physics) -> SensorModel:
    try:
        return _cached_sensor(physics)
    except TypeError:  # a Physics built with lists is not hashable
        return physics.sensor_model()


@lru_cache(maxsize=64)
def _cached_sensor(physics: Physics) -> SensorModel:
    return physics.sensor_model()


@lru_cache(maxsize=64)
def _phases(seed: int) -> np.ndarray:
    rng = np.random.default_rng([int(seed), 0x9150])
    periods = rng.uniform(0.7, 1.3, size=4) * np.array([1.0, 1.47, 0.83, 2.3])
    phases = rng.uniform(0, 2 * np.pi, size=5)
    return np.concatenate([periods, phases])


def _read_interval(t: np.ndarray, k: np.ndarray, rate_hz: float) -> float:
    """Seconds per read: from the reads asked for when they span more than one, else the
    sensor's own rate."""
    span = int(k.max() - k.min()) if len(k) else 0
    return float(t.max() - t.min()) / span if span > 0 else 1.0 / rate_hz


@lru_cache(maxsize=256)
def _block(seed: int, block: int, glitch_rate: float, glitch_ut: tuple, axis_share: float = 0.0,
           radial_share: float = 0.0):
    rng = np.random.default_rng([int(seed), 0xA8975, block])
    noise = rng.standard_normal((_BLOCK, 3))
    glitch, along = glitch_parts(rng, _BLOCK, glitch_rate, glitch_ut, axis_share, radial_share)
    along = np.zeros(_BLOCK) if along is None else along
    for a in (noise, glitch, along):
        a.setflags(write=False)
    return noise, glitch, along


def _accel_noise(seed: int, k: np.ndarray) -> np.ndarray:
    """Unit white noise of the accelerometer reads ``k``, (n, 3): a function of (seed, k) only."""
    out = np.empty((len(k), 3))
    for b in np.unique(k // _BLOCK):
        sel = (k // _BLOCK) == b
        out[sel] = _accel_block(int(seed), int(b))[k[sel] % _BLOCK]
    return out


@lru_cache(maxsize=64)
def _accel_block(seed: int, block: int) -> np.ndarray:
    noise = np.random.default_rng([int(seed), 0xACCE1, block]).standard_normal((_BLOCK, 3))
    noise.setflags(write=False)
    return noise


def demo_scenario(seed: int = 1) -> Scenario:
    """The embedded default: a board with realistic hard iron and a little soft iron."""
    return Scenario(
        physics=Physics(
            hard_iron_ut=(23.5, -41.2, 12.8),
            distortion=((1.012, 0.004, -0.003), (0.004, 0.991, 0.002), (-0.003, 0.002, 1.004)),
            noise_ut=0.4,
        ),
        motion=Motion("sphere", period_s=20.0),
        temperature=Temperature(base_c=27.0, swing_c=1.5),
        seed=seed,
    )
