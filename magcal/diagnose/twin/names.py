"""Where a recording and its twins disagree, and what physics that names (numerics + words).

``locate`` turns the per-block and per-direction-cell pieces of the battery into the time
windows and directions where the recording leaves its twins' 2.5–97.5 % band; ``mismatches``
names each statistic outside its band with the effect that would explain it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import timewords
from . import stats as ts


@dataclass(frozen=True)
class Mismatch:
    statistic: str
    side: str  # "high" or "low": the recording against its twins
    effect: str  # the effect that would explain it
    summary: str  # in physics words, with where it sits

    def to_dict(self) -> dict:
        return {"statistic": self.statistic, "side": self.side, "effect": self.effect, "summary": self.summary}

# statistic → (effect, words when the recording is higher, words when lower)
_NAMES = {
    "rms_ut": ("noise", "the |field| spreads more than the model's noise and terms explain",
               "the |field| spreads less than modelled: the model's noise or wander is too large"),
    "tail_ratio": ("disturbances", "heavier tails than the model: intermittent disturbances of the field "
                   "(moving iron, a switched current) or glitches",
                   "lighter tails than the model's disturbances and glitches give"),
    "lag1": ("wander", "the residual is smoother sample to sample than the model's: slow offset wander "
             "or the sensor's own low-pass filter", "the residual is rougher than modelled: less slow wander"),
    "slow_share": ("wander", "more of the residual lives at periods of a second and longer: slow offset "
                   "wander", "less slow variance than the model's wander gives"),
    "block_wander_ut": ("wander", "the offset moves between time blocks more than modelled: drift, steps "
                        "or an unlogged temperature", "the offset is steadier than the model's wander"),
    "psd_slope": ("wander", "a flatter residual spectrum than modelled (whiter)",
                  "the residual spectrum falls faster with frequency than modelled: a redder wander "
                  "(random-walk-like)"),
    "harmonic_share": ("nonlinearity", "a degree-3/4 direction pattern: a nonlinear transfer, a saturation "
                       "cap or a field gradient that follows the motion", "less degree-3/4 pattern than modelled"),
    "gain_deviation": ("soft_iron", "the free ellipsoid's gains differ more than modelled: soft iron, axis "
                       "scale mismatch or non-orthogonality left out", "less soft iron than modelled"),
    "direction_bias_ut": ("soft_iron", "the residual depends on the field direction: soft iron or a "
                          "nonlinearity left out", "less direction-dependent error than modelled"),
    "glitch_rate": ("glitches", "more isolated jumps than modelled", "fewer isolated jumps than modelled"),
    "repeat_share": ("repeats", "more reads repeat the one before, bit for bit, than modelled: the host reads "
                     "faster than the sensor converts", "fewer repeated reads than modelled"),
}
_TIME = {"block_wander_ut", "slow_share", "lag1", "psd_slope", "tail_ratio", "rms_ut"}
_DIRECTION = {"harmonic_share", "direction_bias_ut", "gain_deviation"}


def _band(values: list, q=(2.5, 97.5)) -> tuple[np.ndarray, np.ndarray]:
    """The twins' band per column; NaN where no twin has a value (a direction cell none visits)."""
    a = np.array(values, dtype=np.float64)
    lo, hi = np.full(a.shape[1:], np.nan), np.full(a.shape[1:], np.nan)
    seen = np.isfinite(a).any(axis=0)
    if seen.any():
        lo[seen], hi[seen] = np.nanpercentile(a[:, seen], q, axis=0)
    return lo, hi


def locate(real: dict, twins: list[dict], t_s: np.ndarray) -> dict:
    """The blocks (time windows) and direction cells where the recording is outside its twins'
    band, with the bands themselves for pictures."""
    out = {"blocks_real": real["blocks"], "cells_real": real["cells"], "lags": real["lags"]}
    if not twins:
        return out
    nb = min(len(real["blocks"]), *(len(x["blocks"]) for x in twins))
    b_lo, b_hi = _band([x["blocks"][:nb] for x in twins])
    c_lo, c_hi = _band([x["cells"] for x in twins])
    rb, rc = real["blocks"][:nb], real["cells"]
    edges = [float(p[0]) for p in np.array_split(t_s, ts.N_BLOCKS) if len(p)] + [float(t_s[-1])]
    with np.errstate(invalid="ignore"):
        blocks = np.flatnonzero((rb < b_lo) | (rb > b_hi))
        cells = np.flatnonzero(np.isfinite(rc) & ((rc < c_lo) | (rc > c_hi)))
    out.update({"blocks_low": b_lo, "blocks_high": b_hi, "cells_low": c_lo, "cells_high": c_hi,
                "blocks_outside": [int(i) for i in blocks], "cells_outside": [int(i) for i in cells],
                "windows_s": [(edges[i], edges[i + 1]) for i in blocks]})
    return out


def direction_words(cells) -> str:
    """Cells named by their centre direction in the sensor frame (e.g. "+x−z")."""
    centres = ts.cell_centres()
    names = []
    for c in cells:
        v = centres[c]
        parts = [("+" if v[a] > 0 else "−") + "xyz"[a] for a in np.argsort(-np.abs(v)) if abs(v[a]) > 0.35]
        names.append("".join(parts))
    return ", ".join(dict.fromkeys(names))


def _where(name: str, located: dict) -> str:
    if name in _DIRECTION and located.get("cells_outside"):
        return f"; directions {direction_words(located['cells_outside'][:6])}"
    if name in _TIME and located.get("windows_s"):
        w = located["windows_s"][:4]
        return "; time " + ", ".join(timewords.stretch(a, b, ".0f") for a, b in w)
    return ""


def mismatches(bands, located: dict) -> tuple:
    """One named Mismatch per statistic outside its band."""
    out = []
    for b in bands:
        if b.inside:
            continue
        if b.name.startswith("xcorr:"):
            ch = b.name.split(":", 1)[1]
            lag = located.get("lags", {}).get(ch, 0.0)
            words = (f"the residual follows {ch} (|r| = {b.real:.2f} at lag {timewords.duration(lag, '+.2f')}): an offset "
                     f"coupled to it" if b.side == "high" else f"the residual follows {ch} less than modelled")
            out.append(Mismatch(b.name, b.side, ch, words))
            continue
        effect, high, low = _NAMES.get(b.name, ("unknown", "higher than modelled", "lower than modelled"))
        words = (high if b.side == "high" else low) + f" ({b.real:.3g} against {b.low:.3g}–{b.high:.3g})"
        out.append(Mismatch(b.name, b.side, effect, words + _where(b.name, located)))
    return tuple(out)
