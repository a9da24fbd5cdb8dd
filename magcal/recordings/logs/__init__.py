"""Flight logs in: PX4 ULog (.ulg, through pyulog) and ArduPilot DataFlash (.bin/.log, through
pymavlink), both from the optional extra ``logs`` (``pip install 'magcal-mpu9150[logs]'``).

``read_log(path)`` → FlightLog (streams as logged); ``select(log, mag)`` → LogMag (one
magnetometer, the log's calibration undone, everything on its timestamps, the expected field);
``load_log_series(path, mag)`` → the Series the rest of magcal reads. A damaged log is read up
to the damage with a warning. A log with several magnetometers and no ``mag`` raises
MagnetometerChoice (an InputError) that lists them.
"""

from __future__ import annotations

from ...core.errors import ExtraMissing, InputError
from .select import MagnetometerChoice, choose, select
from .values import FlightLog, LogMag, MagInfo, Stream

EXTRA_HINT = "pip install 'magcal-mpu9150[logs]'"
HEAD_BYTES = 16


def log_kind(head: bytes) -> str | None:
    """'ulog', 'dataflash' or None, from a file's first bytes."""
    from .dataflash import is_dataflash
    from .ulog import is_ulog

    if is_ulog(head):
        return "ulog"
    if is_dataflash(head):
        return "dataflash"
    return None


def _need(module: str, kind: str, path: str):
    try:
        __import__(module)
    except ImportError as exc:
        raise ExtraMissing(f"{path}: reading a {kind} needs {module}, which comes with the optional extra 'logs': "
                         f"{EXTRA_HINT}") from exc


def read_log(path: str) -> FlightLog:
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    kind = log_kind(head)
    if kind is None:
        raise InputError(f"{path}: not a PX4 ULog or ArduPilot DataFlash log")
    try:
        if kind == "ulog":
            _need("pyulog", "PX4 ULog", path)
            from . import ulog

            return ulog.read(path)
        _need("pymavlink", "DataFlash log", path)
        from . import dataflash

        return dataflash.read(path, head)
    except InputError:
        raise
    except Exception as exc:  # a parser that gives up before the first message: say so plainly
        raise InputError(f"{path}: the {kind} parser could not read this file ({type(exc).__name__}: {exc})") from exc


def load_log(path: str, mag: int | None) -> LogMag:
    return select(read_log(path), mag)


def load_log_series(path: str, mag: int | None):
    return load_log(path, mag).series


__all__ = ["FlightLog", "LogMag", "MagInfo", "Stream", "MagnetometerChoice", "read_log", "load_log",
           "load_log_series", "log_kind", "choose", "select", "EXTRA_HINT"]
