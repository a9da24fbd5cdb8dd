"""A capture cut to its first N samples: ``record --count N`` keeps exactly N when the source
handed over more in its last read."""

from __future__ import annotations

import os

from ..wire.dialect import Dialect
from .capture import CaptureReader, CaptureWriter, recorded_dialect


def keep_first_samples(path, n: int) -> bool:
    """Rewrite a protocol-v1 capture so it ends just before its (n+1)-th sample line: a source
    that hands over many samples per read leaves more bytes recorded than were asked for, and
    ``record --count N`` keeps N. True when something was cut (never for other dialects)."""
    reader = CaptureReader(path)
    if recorded_dialect(reader) is not Dialect.NATIVE:
        return False
    pos = reader.frames().pos
    if len(pos) <= n:
        return False
    cut, done = int(pos[n]), 0
    tmp = os.fspath(path) + ".cut"
    with CaptureWriter(tmp, reader.header) as w:
        for t, chunk in reader:
            if done >= cut:
                break
            w.append(chunk[: cut - done], t_rx_s=t)
            done += len(chunk)
    os.replace(tmp, path)
    return True
