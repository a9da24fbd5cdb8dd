"""The reading's lattice: the step a sensor's readings sit on (its quantum), from the readings.

A module of its own, light to import: the twin as the null needs it on every wandering
recording, and the twin's comparison module (magcal.diagnose.twin) imports scipy.
"""

from __future__ import annotations

import numpy as np


def quantum(m: np.ndarray) -> tuple:
    """Per axis, the reading's step when the values sit on a lattice, else 0."""
    out = []
    for a in range(3):
        v = np.unique(m[:, a])
        d = np.diff(v)
        d = d[d > 1e-12]
        if len(d) < 10:
            out.append(0.0)
            continue
        q = float(np.percentile(d, 5))
        on_grid = np.abs(d / q - np.round(d / q)) < 0.02
        out.append(q if np.mean(on_grid) > 0.95 else 0.0)
    return tuple(out)
