"""Channels that cannot be candidates: those that follow the board's orientation or the reading.

An offset term K·x of a channel x that is itself a function of the field direction u — an
accelerometer or attitude angle, a quaternion, the same magnetometer in raw counts, a flight
controller's own estimate of the magnetometer's offset — is a direction-dependent error: it
competes with hard and soft iron for the same residual, and every such column offered makes
soft iron less identifiable. A gyro's rate is the field direction's own rate of change
(du/dt = −ω × u) and competes the same way. Such channels are left out of the candidates, each
with a line saying which and why, recognised

* by name: tokens of the column name (``acc_x_g``, ``imu_gx``, ``mag_x_counts``, ``q0``,
  ``roll``, ``fc_bias_est_x`` …), see ``KINDS``;
* by test: the share of the channel's variance explained by the field direction — polynomials
  of degree ≤ 4 in u, its rate of change u̇ and u × u̇ — at least ``ORIENTATION_SHARE``, and
  clearly more than a smooth curve in time explains (a slow channel during one slow sweep is
  explained by both, and is left to the tests, which say when it cannot be told apart).

The temperature, the current and time themselves (``temp_c``, ``current_a``, ``t_s``) are never
left out here. Naming the channels (``--channels``) skips this screen.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from itertools import combinations_with_replacement

import numpy as np
from numpy.polynomial import legendre

from . import channels

ORIENTATION_SHARE = 0.5  # share of variance explained by the field direction
TIME_MARGIN = 0.25  # … by this much more than a degree-TIME_DEGREE curve in time
TIME_DEGREE = 6
SMOOTH = 5  # samples averaged before the direction is differentiated

KINDS = {
    "a magnetometer reading (the same field, in another unit or from another sensor)": {
        "mag", "magn", "magnetometer", "compass", "mx", "my", "mz", "bx", "by", "bz", "rm3100", "pni",
        "hmc", "qmc", "ak8963", "ak8975", "ak09916", "lis3mdl", "fluxgate",
    },
    "an accelerometer (gravity in the sensor frame follows the orientation)": {
        "acc", "accel", "acceleration", "accelerometer", "ax", "ay", "az", "grav", "gravity",
    },
    "a gyro (the rotation rate is the field direction's own rate of change)": {
        "gyro", "gyr", "gx", "gy", "gz", "omega", "dps",
    },
    "an attitude angle": {"roll", "pitch", "yaw", "heading", "attitude", "euler", "rpy", "azimuth", "tilt", "inclination"},
    "a quaternion component": {"quat", "quaternion", "q0", "q1", "q2", "q3", "qw", "qx", "qy", "qz"},
    "an estimator's own offset estimate": {"bias", "offset", "est", "estimate", "estimator"},
}
KEEP = {channels.TEMP, channels.CURRENT, channels.TIME}


@dataclass(frozen=True)
class LeftOut:
    """A channel left out of the candidates, and why."""

    channel: str
    kind: str  # what it is (from its name), or "" when recognised by the test alone
    orientation_share: float  # share of its variance the field direction explains

    @property
    def why(self) -> str:
        share = f"{100 * self.orientation_share:.0f} % of its variance follows the field direction"
        return f"{self.kind}; {share}" if self.kind else f"it follows the board's orientation: {share}"


def tokens(name: str) -> list[str]:
    """Lower-case words of a column name: ``fc_bias_est_x`` → fc, bias, est, x; ``magX`` → mag, x."""
    spaced = re.sub(r"([a-z])([A-Z])", r"\1 \2", name)
    return [t for t in re.split(r"[^a-z0-9]+", spaced.lower()) if t]


def kind_by_name(name: str) -> str:
    words = set(tokens(name))
    for kind, names in KINDS.items():
        if words & names:
            return kind
    return ""


def _smoothed(u: np.ndarray) -> np.ndarray:
    kernel = np.ones(SMOOTH) / SMOOTH
    return np.stack([np.convolve(u[:, j], kernel, mode="same") for j in range(3)], axis=1)


def direction_functions(u: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 31): polynomials of degree ≤ 4 in u, u̇ and u × u̇ (u̇ from the smoothed directions)."""
    cols = [np.ones((len(u), 1))]
    for deg in (1, 2, 3, 4):
        cols.append(np.stack([np.prod(u[:, list(c)], axis=1) for c in combinations_with_replacement(range(3), deg)], axis=1))
    us = _smoothed(u)
    du = np.gradient(us, t, axis=0) if np.all(np.diff(t) > 0) else np.gradient(us, axis=0)
    cols += [du, np.cross(us, du)]
    return np.concatenate(cols, axis=1)


def _share(f: np.ndarray, x: np.ndarray) -> float:
    xc = x - x.mean()
    total = float(xc @ xc)
    if total <= 0:
        return 0.0
    coef = np.linalg.lstsq(f, xc, rcond=None)[0]
    return max(0.0, 1.0 - float(np.sum((xc - f @ coef) ** 2)) / total)


def screen(chans: dict, u: np.ndarray, t: np.ndarray) -> tuple[dict, tuple]:
    """(the channels kept as candidates, the LeftOut ones) for unit field directions u and
    times t; ``chans`` maps names to arrays on the same samples."""
    f_dir = direction_functions(u, t)
    tau = np.linspace(-1.0, 1.0, len(t))
    f_time = legendre.legvander(tau, TIME_DEGREE)
    kept, left = {}, []
    for name, x in chans.items():
        if name in KEEP or not np.all(np.isfinite(x)):
            kept[name] = x
            continue
        share = _share(f_dir, x)
        kind = kind_by_name(name)
        by_test = share >= ORIENTATION_SHARE and share >= _share(f_time, x) + TIME_MARGIN
        if kind or by_test:
            left.append(LeftOut(name, kind, share))
        else:
            kept[name] = x
    return kept, tuple(left)
