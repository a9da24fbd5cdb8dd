"""Degree-3 and degree-4 real spherical harmonics: the direction nonlinearity of the sensor model.

A linear sensor error (offset, soft iron, scale, non-orthogonality) leaves degree ≤ 2 in the
radial residual |h| − r as a function of the unit field direction u (docs/sensor-model.md). What
is left at degree 3 and 4 is not linear: saturation caps, a non-linear transfer, a field
gradient that follows the motion. These 16 functions span it. Each is scaled to unit RMS over
the sphere, so a coefficient in µT is the RMS radial error that term adds.

>>> import numpy as np
>>> u = np.array([[0.0, 0.0, 1.0]])
>>> basis(u).shape
(1, 16)
"""

from __future__ import annotations

import numpy as np

NAMES = (
    "y3_m3", "y3_m2", "y3_m1", "y3_0", "y3_p1", "y3_p2", "y3_p3",
    "y4_m4", "y4_m3", "y4_m2", "y4_m1", "y4_0", "y4_p1", "y4_p2", "y4_p3", "y4_p4",
)


def _raw(u: np.ndarray) -> np.ndarray:
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    x2, y2, z2 = x * x, y * y, z * z
    return np.column_stack([
        y * (3 * x2 - y2), x * y * z, y * (5 * z2 - 1), z * (5 * z2 - 3),
        x * (5 * z2 - 1), z * (x2 - y2), x * (x2 - 3 * y2),
        x * y * (x2 - y2), y * z * (3 * x2 - y2), x * y * (7 * z2 - 1), y * z * (7 * z2 - 3),
        35 * z2 * z2 - 30 * z2 + 3, x * z * (7 * z2 - 3), (x2 - y2) * (7 * z2 - 1),
        x * z * (x2 - 3 * y2), x2 * (x2 - 3 * y2) - y2 * (3 * x2 - y2),
    ])


def _fibonacci(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    s = np.sqrt(1 - z * z)
    return np.column_stack([s * np.cos(phi), s * np.sin(phi), z])


_SCALE = 1.0 / np.sqrt(np.mean(_raw(_fibonacci(20000)) ** 2, axis=0))


def basis(u) -> np.ndarray:
    """(n, 16): the 16 functions at the unit directions ``u`` (n, 3), each of unit RMS."""
    u = np.atleast_2d(np.asarray(u, dtype=np.float64))
    return _raw(u) * _SCALE


def radial_ut(u, coef_ut) -> np.ndarray:
    """The radial error Σ c_j Y_j(u) in µT at directions ``u`` (n, 3)."""
    c = np.asarray(coef_ut, dtype=np.float64).reshape(len(NAMES))
    return basis(u) @ c
