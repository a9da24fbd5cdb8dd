"""The parametric bootstrap (``compare``): the recording's own times, channels and field
directions drive ``draws`` twins of the model; each twin is refitted with the same calibration
model as the recording and the statistics of ``stats`` computed on both. A statistic whose
real value lies outside the 2.5–97.5 % band of its twins is a mismatch, located and named
(``names``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...core.series import Series
from ...sim.model import SensorModel
from .. import timewords
from . import stats as ts
from .draw import twin_directions, twin_draw
from .names import locate, mismatches
from .residual import RefitResidual, refit, with_time
from .stats import repeats


DRAWS = 50
BAND = (2.5, 97.5)
# channels that follow the orientation or are the magnetometer itself: not offered as couplings
ORIENTATION_WORDS = ("mag", "acc", "gyro", "quat", "roll", "pitch", "yaw", "bias", "att")


@dataclass(frozen=True)
class Band:
    """A statistic of the recording against the spread of its twins."""

    name: str
    real: float
    low: float
    high: float
    median: float

    @property
    def inside(self) -> bool:
        return bool(self.low <= self.real <= self.high) if np.isfinite(self.real) else True

    @property
    def side(self) -> str:
        return "inside" if self.inside else ("high" if self.real > self.high else "low")

    def to_dict(self) -> dict:
        return {"real": _num(self.real), "twin_low": _num(self.low), "twin_high": _num(self.high),
                "twin_median": _num(self.median), "inside": self.inside}


@dataclass(frozen=True)
class StepComparison:
    """One step's model against the recording: each statistic's band, the mismatches, where they sit."""

    step: str
    effects: tuple
    bands: tuple
    mismatches: tuple
    draws: int
    located: dict = field(default_factory=dict, repr=False)  # real and twin-band pieces
    real: RefitResidual | None = field(default=None, repr=False)
    twin: RefitResidual | None = field(default=None, repr=False)  # one twin draw, for pictures

    @property
    def inside(self) -> int:
        return sum(b.inside for b in self.bands)

    def to_dict(self) -> dict:
        return {"step": self.step, "effects": list(self.effects), "draws": self.draws,
                "inside": self.inside, "statistics": len(self.bands),
                "bands": {b.name: b.to_dict() for b in self.bands},
                "mismatches": [m.to_dict() for m in self.mismatches]}


def _num(x):
    x = float(x)
    return x if np.isfinite(x) else None


@timewords.in_recording_time
def compare(model: SensorModel, series: Series, draws: int = DRAWS, seed: int = 0, step: str = "final",
            free: bool = True) -> StepComparison:
    """The parametric bootstrap of ``model`` against ``series`` (valid samples). A statistic
    the recording cannot give (NaN: e.g. direction terms on a still board) is left out."""
    s = series.only_valid()
    chans = with_time(s)
    real = refit(model, s.field_ut, s.t_s, chans, free)
    if real is None:
        raise ValueError("the model's calibration cannot be refitted to the recording")
    shown = {k: v for k, v in s.channels.items() if not any(w in k.lower() for w in ORIENTATION_WORDS)}
    again = bool(repeats(real.m).any())
    stats_real, loc_real = ts.battery(real.e, real.u, real.m, real.t, shown, real.gain if free else float("nan"), again)
    stats_real = {k: v for k, v in stats_real.items() if np.isfinite(v)}
    sims, locs, first = [], [], None
    u = twin_directions(model, s)
    for i in range(draws):
        x = twin_draw(model, s, seed + i, free, u)
        if x is None:
            continue
        first = first or x
        st, lo = ts.battery(x.e, x.u, x.m, x.t, {k: x.channels[k] for k in shown}, x.gain if free else float("nan"),
                            again)
        sims.append(st)
        locs.append(lo)
    bands = tuple(_band(k, v, [d.get(k, np.nan) for d in sims]) for k, v in stats_real.items())
    located = locate(loc_real, locs, s.t_s)
    return StepComparison(step=step, effects=model.effects(), bands=bands,
                      mismatches=mismatches(bands, located), draws=len(sims), located=located,
                      real=real, twin=first)


def _band(name: str, real: float, values) -> Band:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return Band(name, real, -np.inf, np.inf, float("nan"))
    lo, mid, hi = np.percentile(v, [BAND[0], 50.0, BAND[1]])
    return Band(name, float(real), float(lo), float(hi), float(mid))
