"""Samples from a capture's parsed frames, exactly as the live client builds them: the field
by the latest hello's ASA and chip (its µT per count, its rails, its die-temperature formula),
device time unwrapped per reset epoch, validity by ``Sample.valid``'s rules."""

from __future__ import annotations

import numpy as np

from ..core.chips import MPU9150, Chip, chip_from_ids
from ..core.sample import ST2_DERR, ST2_HOFL, UT_PER_COUNT, asa_gain
from ..core.series import Series
from ..wire.bulk import Frames
from ..wire.protocol import ACCEL_COUNTS_PER_G, Hello, Restart, hello_applies


# -- samples from frames, exactly as the live client builds them ---------------------------
def series_from_frames(frames: Frames) -> Series:
    """The Series a passive ``ProtocolDevice`` reading the same bytes would collect:
    field from the latest hello's ASA (unity before any hello), device time unwrapped per
    reset epoch, validity by ``Sample.valid``'s rules. Bit-identical (tests hold it). Built
    ``_ROWS`` samples at a time, so the temporaries stay small beside the result."""
    n = len(frames)
    hellos, refused = _applied_hellos(frames)
    h_pos = np.array([p for p, _ in hellos], np.int64)
    gains = np.array([[1.0, 1.0, 1.0]] + [[asa_gain(a) for a in m.asa] for _, m in hellos], np.float64)
    chips = _ChipTable([MPU9150] + [_hello_chip(m) for _, m in hellos])
    r_pos = np.array([p for p, e in frames.events if isinstance(e, Restart)], np.int64)
    field = np.empty((n, 3), np.float64)
    t = np.empty(n, np.float64)
    valid = np.empty(n, bool)
    temp_c = np.empty(n, np.float64)
    for a in range(0, n, _ROWS):
        b = min(n, a + _ROWS)
        _field_rows(frames, a, b, h_pos, (gains, chips), (field, valid, temp_c))
        _time_rows(frames, a, b, r_pos, t)
    raw_kind = frames.kind == ord("S")
    channels = {"temp_c": temp_c} if n else {}
    if n and not np.isnan(frames.accel).all():  # the accelerometer, as the live client names it (NaN: none sent)
        channels.update(_accel_channels(frames, h_pos, chips))
    if n and not raw_kind.all():
        channels["calibrated"] = np.where(raw_kind, np.nan, 1.0)
    reading = {**frames.counters, "hellos_refused": refused}
    return Series(t_s=t, field_ut=field, channels=channels, valid=valid, seq=frames.seq.copy(), reading=reading)


_ROWS = 1 << 17  # samples per step of series_from_frames


def _accel_channels(frames: Frames, h_pos, chips: "_ChipTable") -> dict:
    """``ax_g, ay_g, az_g`` as the live client makes them (``protocol_client.accel_aux``): the
    IMU's counts turned into the magnetometer's axes by the chip of the hello before each sample."""
    which = np.searchsorted(h_pos, frames.pos)
    rows, out = np.arange(len(which)), {}
    for i, name in enumerate(("ax_g", "ay_g", "az_g")):
        out[name] = chips.accel_sign[which, i] * frames.accel[rows, chips.accel_axis[which, i]] / ACCEL_COUNTS_PER_G
    return out


def _hello_chip(hello: Hello) -> Chip:
    """The part a hello names (the MPU-9150 for ids no known part answers), exactly as the
    live client reads it (``protocol_client.hello_chip``)."""
    try:
        return chip_from_ids(hello.who_am_i, hello.wia, hello.bits or None)
    except ValueError:
        return MPU9150


class _ChipTable:
    """Per hello (row 0: before any), the chip's figures as arrays: its count over the
    AK8975's, its rails, its die-temperature formula and its accelerometer-to-magnetometer axes."""

    def __init__(self, chips: list[Chip]):
        self.scales = np.array([c.ut_per_count / MPU9150.ut_per_count for c in chips], np.float64)
        self.count_min = np.array([c.count_min for c in chips], np.int64)
        self.count_max = np.array([c.count_max for c in chips], np.int64)
        self.temp_lsb_per_c = np.array([c.temp_lsb_per_c for c in chips], np.float64)
        self.temp_offset_c = np.array([c.temp_offset_c for c in chips], np.float64)
        self.accel_axis = np.array([[k for k, _ in c.mag_from_accel] for c in chips], np.int64)
        self.accel_sign = np.array([[sgn for _, sgn in c.mag_from_accel] for c in chips], np.float64)


def _field_rows(frames: Frames, a: int, b: int, h_pos, gains_chips, out_rows) -> None:
    """Field (µT), validity and die temperature (°C) of samples ``a`` … ``b-1``, each by the
    chip of the hello before it; ``gains_chips``: each hello's ASA gains and ``_ChipTable``."""
    gains, chips = gains_chips
    field, valid, temp_c = out_rows
    scales = chips.scales
    which = np.searchsorted(h_pos, frames.pos[a:b])  # 0: before any hello
    temp_c[a:b] = frames.temp[a:b] / chips.temp_lsb_per_c[which] + chips.temp_offset_c[which]
    raw_kind = frames.kind[a:b] == ord("S")
    vals = frames.values[a:b]
    out = field[a:b]
    # the live client's counts_to_ut(raw, asa) * (chip µT/count / 0.3), element by element
    w = which[raw_kind]
    out[raw_kind] = vals[raw_kind].astype(np.float64) * (UT_PER_COUNT * gains[w]) * scales[w][:, None]
    out[~raw_kind] = vals[~raw_kind].astype(np.float64) / 1000.0
    st2_bad = (frames.st2[a:b] & (ST2_DERR | ST2_HOFL)) != 0
    rails = np.any((vals <= chips.count_min[which][:, None]) | (vals >= chips.count_max[which][:, None]), axis=1)
    zero = np.all(vals == 0, axis=1)
    valid[a:b] = ~st2_bad & np.where(raw_kind, ~rails & ~zero, True)


def _time_rows(frames: Frames, a: int, b: int, r_pos, t) -> None:
    """Device time of samples ``a`` … ``b-1``: t_k = t_{k-1} + Δ, with Δ = ms/1000 at the
    start of an epoch (after a reset), else the ms step (mod 2³²) / 1000; summed in order, so
    the figures equal one pass over all samples."""
    p = max(a - 1, 0)  # the sample before, for the step and the epoch
    epoch = np.searchsorted(r_pos, frames.pos[p:b], side="right")
    ms = frames.ms[p:b]
    first = np.ones(len(ms), bool)
    first[1:] = epoch[1:] != epoch[:-1]
    step = np.zeros(len(ms), np.int64)
    step[1:] = (ms[1:] - ms[:-1]) % (1 << 32)
    inc = np.where(first, ms / 1000.0, step / 1000.0)[a - p :]
    if a:
        inc[0] = t[a - 1] + inc[0]
    t[a:b] = np.cumsum(inc)


def _applied_hellos(frames: Frames) -> tuple[list, int]:
    """The hellos that set the gain of later samples, by the live client's rule
    (``hello_applies``), and how many were refused."""
    out, current, refused = [], None, 0
    for p, m in frames.others:
        if isinstance(m, Hello):
            if hello_applies(current, m):
                out.append((p, m))
                current = m
            else:
                refused += 1
    return out, refused
