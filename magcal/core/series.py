"""Series: a recording as column arrays (a value; the offline counterpart of a Sample stream).

``t_s`` (n,) seconds, ``field_ut`` (n, 3) ASA-adjusted µT in the sensor frame, ``channels``
maps an auxiliary channel name (``temp_c``, ``current_a`` …) to an (n,) array, ``seq`` the
device sequence numbers when known, ``valid`` False for samples the device flagged (HOFL, DERR,
rails, all-zero). ``row`` maps each sample back to its 0-based data row in the source file;
``source`` says how a table was read (which columns, which units), when it was one;
``reading`` counts what reading the file met (framing defects, duplicates, lost lines, damaged
chunks, lines left out, by name) so that none of it passes silently.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterable, Mapping

import numpy as np

from .sample import Sample


@dataclass(frozen=True)
class Series:
    t_s: np.ndarray
    field_ut: np.ndarray
    channels: Mapping[str, np.ndarray] = field(default_factory=dict)
    valid: np.ndarray | None = None
    seq: np.ndarray | None = None
    row: np.ndarray | None = None
    source: str | None = None  # how a table was read (columns, units), for the user to check
    reading: Mapping[str, int] = field(default_factory=dict)  # what reading met: counts by name
    clock: bool = True  # False: the source gave no time, and t_s is the sample index
    unit_assumed: bool = False  # True: the source named no unit for the field, µT was assumed

    def __post_init__(self):
        f = np.asarray(self.field_ut, dtype=np.float64).reshape(-1, 3)
        n = len(f)
        t = np.asarray(self.t_s, dtype=np.float64).reshape(-1)
        if len(t) != n:
            raise ValueError(f"t_s has {len(t)} rows but field_ut has {n}")
        ch = {}
        for k, v in dict(self.channels).items():
            a = np.asarray(v, dtype=np.float64).reshape(-1)
            if len(a) != n:
                raise ValueError(f"channel {k!r} has {len(a)} rows, expected {n}")
            ch[k] = a
        valid = np.ones(n, bool) if self.valid is None else np.asarray(self.valid, bool).reshape(-1)
        row = np.arange(n) if self.row is None else np.asarray(self.row, np.int64).reshape(-1)
        object.__setattr__(self, "field_ut", f)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "channels", ch)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "row", row)
        object.__setattr__(self, "reading", {str(k): int(v) for k, v in dict(self.reading).items() if v})
        if self.seq is not None:
            object.__setattr__(self, "seq", np.asarray(self.seq, np.int64).reshape(-1))

    def __len__(self) -> int:
        return len(self.field_ut)

    def take(self, idx) -> "Series":
        """A sub-series (boolean mask or index array); rows keep pointing at the source file."""
        return Series(
            t_s=self.t_s[idx],
            field_ut=self.field_ut[idx],
            channels={k: v[idx] for k, v in self.channels.items()},
            valid=self.valid[idx],
            seq=None if self.seq is None else self.seq[idx],
            row=self.row[idx],
            source=self.source,
            reading=self.reading,
            clock=self.clock,
            unit_assumed=self.unit_assumed,
        )

    def thinned(self, max_n: int) -> tuple["Series", int]:
        """(every k-th sample, k): at most ``max_n`` samples, spread evenly over the whole
        recording; k = 1 (the series itself) when it is no longer. ``reading`` notes a thinning."""
        k = -(-len(self) // max_n) if len(self) > max_n else 1
        if k == 1:
            return self, 1
        out = self.take(slice(None, None, k))
        return replace(out, reading={**self.reading, "thinned_every": k, "samples_read": len(self)}), k

    def only_valid(self) -> "Series":
        return self if self.valid.all() else self.take(self.valid)

    @classmethod
    def from_samples(cls, samples: Iterable[Sample]) -> "Series":
        samples = list(samples)
        n = len(samples)
        t = np.fromiter((s.t_s for s in samples), np.float64, n)
        f = np.array([s.field_ut for s in samples], dtype=np.float64).reshape(n, 3)
        channels: dict[str, np.ndarray] = {}
        if n and all(s.temp_c is not None for s in samples):
            channels["temp_c"] = np.fromiter((s.temp_c for s in samples), np.float64, n)
        names = set().union(*(s.aux.keys() for s in samples)) if n else set()
        for name in sorted(names):
            channels[name] = np.array([s.aux.get(name, np.nan) for s in samples], np.float64)
        valid = np.fromiter((s.valid for s in samples), bool, n)
        seq = np.fromiter((s.seq for s in samples), np.int64, n)
        return cls(t_s=t, field_ut=f, channels=channels, valid=valid, seq=seq)
