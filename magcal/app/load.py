"""Any recording file → ``Series``: a magcal capture, a table (magcal's CSV or anyone's
delimited text), a MotionCal log, or a raw protocol-v1 byte dump, told apart by content.

Recorded bytes are decoded by the same client that reads a live port (a passive device on the
recorded bytes), so a recording yields the samples the live run saw.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Iterator, NamedTuple

from ..core.errors import DeviceError, InputError
from ..core.series import Series
from ..recordings.capture import BLOCK_BYTES, MAX_HEADER, CaptureReader, is_capture, recorded_dialect, series_from_frames
from ..recordings.logs import HEAD_BYTES, LogMag, load_log, log_kind
from ..recordings.table import TableFormat, load_table, looks_like_table
from ..wire import motioncal
from ..wire.dialect import Dialect
from ..wire.bulk import Frames, parse_blocks
from ..wire.protocol import CalibratedSample, RawSample


def load_capture(path) -> Series:
    """A capture's samples, read by the live link's rules; damage to the chunk structure is
    read around and counted (``Series.reading``)."""
    reader = CaptureReader(path)
    if recorded_dialect(reader) is Dialect.MOTIONCAL:
        series = _motioncal_capture(reader)
    else:
        series = _native_series(reader.frames(), reader.data, str(path))
    return replace(series, reading={**series.reading, **reader.reading()})


def _native_series(frames: Frames, whole: Callable[[], bytes], name: str) -> Series:
    """The samples of protocol v1 bytes already parsed to ``frames``; ``whole`` gives the
    bytes again for the rare stream the fast arrays cannot hold."""
    if any(isinstance(m, (RawSample, CalibratedSample)) for _, m in frames.others):
        # a number too large for the fast arrays: take the live client's path instead
        return _raw_only(_series_via_device(whole(), name), name)
    return _raw_only(series_from_frames(frames), name)


def _file_blocks(path) -> Iterator[bytes]:
    with open(path, "rb") as fh:
        while block := fh.read(BLOCK_BYTES):
            yield block


def _read_all(path) -> bytes:
    with open(path, "rb") as fh:
        return fh.read()


def _series_via_device(data: bytes, name: str) -> Series:
    from ..devices.base import read_to_end
    from ..devices.replay import BytesTransport, recorded_device

    dev = recorded_device(name, BytesTransport([(0.0, data)]))
    series = Series.from_samples(read_to_end(dev))
    return replace(series, reading={**dev.framer.counters, "hellos_refused": dev.counters["hellos_refused"]})


def _raw_only(series: Series, name: str) -> Series:
    """The raw readings only: calibrated (``U``) lines — the device's own output in calibrated
    mode — are not raw data and are left out (counted as ``calibrated_lines``), as the live
    session rejects them."""
    flag = series.channels.get("calibrated")
    if flag is None:
        return series
    cal = flag == 1.0
    n_cal = int(cal.sum())
    if n_cal == len(series):
        raise InputError(f"{name}: all {n_cal} sample lines are calibrated (U) readings, which cannot be "
                         "fitted; record the device's raw output (magcal record, or the daemon's capture)")
    kept = series.take(~cal)
    channels = {k: v for k, v in kept.channels.items() if k != "calibrated"}
    return replace(kept, channels=channels, reading={**series.reading, "calibrated_lines": n_cal})


def _motioncal_capture(reader: CaptureReader) -> Series:
    """A MotionCal-dialect capture read as it was live (the same device on the recorded bytes):
    each reading timed by when its bytes arrived."""
    from ..devices.base import read_to_end
    from ..devices.replay import BytesTransport, recorded_device

    dev = recorded_device(str(reader.path), BytesTransport(reader), Dialect.MOTIONCAL)
    try:
        return Series.from_samples(read_to_end(dev))
    except DeviceError as exc:
        raise InputError(str(exc)) from None


# -- any recording -------------------------------------------------------------------------
class Loaded(NamedTuple):
    """A recording as read: its samples, the reading's warnings (a damaged flight log read up to
    the damage) and, for a flight log, the magnetometer as read (``LogMag``: the attitude, the
    expected field and the parameters a log-aware step needs; None otherwise)."""

    series: Series
    warnings: tuple[str, ...]
    log: LogMag | None


def load_series(path, table: TableFormat | None = None, mag: int | None = None) -> Series:
    """The samples of ``load_recording``: what every command but ``diagnose`` needs."""
    return load_recording(path, table, mag).series


def load_recording(path, table: TableFormat | None = None, mag: int | None = None) -> Loaded:
    """A capture, a table (magcal's CSV or other delimited text, read as ``table`` says), a
    MotionCal log, a raw protocol-v1 byte dump, or a flight log (PX4 ULog, ArduPilot DataFlash:
    magnetometer ``mag``), told apart by content. InputError (naming file, line and problem) for
    anything else."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    if not head.strip():
        raise InputError(f"{path}: empty file")
    explicit = table is not None and table.explicit

    def not_a_table(kind: str) -> None:
        if explicit:
            raise InputError(f"{path}: is {kind}, not a table; --columns, --unit and --time apply to tables")

    if log_kind(head[:HEAD_BYTES]):
        not_a_table("a flight log")
        got = load_log(str(path), mag)
        return Loaded(got.series, got.warnings, got)
    if mag is not None:
        raise InputError(f"{path}: --mag chooses a magnetometer of a flight log; this file is not one")
    return Loaded(_series_of_file(path, head, table, explicit, not_a_table), (), None)


def _series_of_file(path, head: bytes, table, explicit: bool, not_a_table) -> Series:
    if is_capture(head):
        not_a_table("a magcal capture")
        return load_capture(path)
    if head.startswith(b"MATLAB"):
        raise InputError(f"{path}: a MATLAB .mat file, which magcal does not read; save the magnetometer "
                         "columns as text (writematrix or csvwrite) and give that file")

    first = _first_lines(head)
    if any("mx" in [c.strip() for c in ln.split(",")] for ln in first[:5]):
        return load_table(path, table)
    if sum(1 for ln in first if ln.startswith("$") and "*" in ln) > len(first) // 2:
        not_a_table("a protocol v1 byte dump")
        return _native_series(parse_blocks(_file_blocks(path)), lambda: _read_all(path), str(path))
    # an Adafruit sketch prints ~30 banner lines (sensor details) before its first Raw: line
    if motioncal is not None and motioncal.looks_like_motioncal(_first_lines(head, 200)):
        not_a_table("a MotionCal log")
        return load_motioncal_log(path)
    if b"\0" in head[:4096] and not explicit:  # (a serial dump with NULs from a reset was taken above)
        raise InputError(f"{path}: a binary file, not a recording magcal reads (a capture, a table, a "
                         "MotionCal log or protocol v1 lines)")
    if explicit or looks_like_table(first):
        return load_table(path, table)  # names the missing columns when it cannot find them
    hint = "" if motioncal is not None else "; MotionCal logs need magcal.motioncal"
    raise InputError(
        f"{path} line 1: not a recording magcal reads (a capture, a table with mx,my,mz columns "
        f"or named by --columns, a MotionCal Raw:/Uni: log, or protocol v1 lines){hint}"
    )


def _first_lines(head: bytes, k: int = 20) -> list[str]:
    text = head.decode("utf-8", "replace").lstrip("\ufeff")
    out = []
    for ln in text.splitlines():
        s = ln.strip()
        if s and not s.startswith("#"):
            out.append(s)
        if len(out) >= k:
            break
    return out


def load_motioncal_log(path, rate_hz: float | None = None) -> Series:
    """Read a saved MotionCal-style log file (``Raw:``/``Uni:`` lines among anything else).
    See ``parse_log`` for the time axis. InputError when the file cannot be read or holds no
    readings."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    return motioncal.parse_log(data, rate_hz=rate_hz, source=str(path))
