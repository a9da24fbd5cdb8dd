"""Is it still the same hard iron? Two fits of one sensor compared through their reported 1σ.

Sessions of the same board drift apart when something near it is magnetised, a battery or a
screw is swapped, or the mounting moved; a calibration from the old session is then wrong by
the difference. ``compare_fits`` takes two fits as ``FitResult.to_dict()`` gives them (so saved
``fit --json`` output works too) and tests the offset change against the two uncertainties
combined: χ² = Σ (Δᵢ / √(σa,ᵢ² + σb,ᵢ²))² with 3 degrees of freedom (the σ already include the
widening for time-correlated residuals). The field magnitude is compared the same way; it
changes with place, not with the board.
"""

from __future__ import annotations

import numpy as np

from .tails import chi2_sf

ALPHA = 0.01


def compare_fits(a: dict, b: dict, alpha: float = ALPHA) -> dict:
    oa, ob = (np.asarray(x["calibration"]["offset_ut"], float) for x in (a, b))
    sa, sb = (np.asarray(x["uncertainty"]["offset_ut"], float) for x in (a, b))
    d = ob - oa
    s = np.hypot(sa, sb)
    chi2 = float(np.sum((d / np.maximum(s, 1e-12)) ** 2))
    p = float(chi2_sf(chi2, 3))
    fa, fb = a["calibration"]["field_ut"], b["calibration"]["field_ut"]
    sf = float(np.hypot(a["uncertainty"]["field_ut"], b["uncertainty"]["field_ut"]))
    return {
        "offset_change_ut": [float(v) for v in d],
        "offset_change_norm_ut": float(np.linalg.norm(d)),
        "offset_change_sigma_ut": [float(v) for v in s],
        "chi2": chi2,
        "p_value": p,
        "offset_moved": p < alpha,
        "field_change_ut": float(fb - fa),
        "field_change_z": float((fb - fa) / max(sf, 1e-12)),
    }
