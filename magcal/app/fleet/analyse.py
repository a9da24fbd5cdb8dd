"""One file of a fleet → its rows, one per magnetometer: the work a worker does.

A flight log is read once and each magnetometer is fitted as ``magcal fit LOG --mag N`` fits it
(``recordings.logs.select`` then ``app.flightlog.fit_flight_log``: the log's calibration undone,
the expected field, the current term judged on held-out blocks). A capture or a table is fitted
as ``magcal fit FILE`` fits it (``app.load.load_series``, thinned to ``max_samples``,
``fit.fit_calibration`` with model auto). What cannot be read or fitted is a row with its
reason: one bad log never ends a run. The row's keys are ``ROW_FIELDS`` (``store`` holds their
types); a row carries nothing of where or when it was computed, so the same file gives the same
rows on any worker.
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from ... import __version__
from ...core.errors import MagcalError

NAN3 = [float("nan")] * 3
TERMS = ("current_a", "motors_on", "throttle")


def _blank(task: dict) -> dict:
    row = {"file_sha256": task["sha256"], "magcal_version": task.get("version", __version__), "path": task["path"],
           "vehicle": task["vehicle"], "vehicle_from": task["vehicle_from"], "notes": task.get("notes", ""),
           "mag_index": -1, "compass": None, "device_id": None, "external": None, "mag_name": None,
           "autopilot": None, "firmware": None, "flight_year": None, "flight_time_utc": None, "duration_s": None,
           "n_samples": None, "n_used": None, "status": "ok", "failure": None, "message": None, "mode": None,
           "model": None, "offset_ut": NAN3, "sigma_offset_ut": NAN3, "soft_iron": [float("nan")] * 9,
           "field_ut": None, "sigma_field_ut": None, "rms_ut": None, "coverage": None, "log_calibration": None}
    for t in TERMS:
        row.update({f"{t}_ut_per_unit": NAN3, f"sigma_{t}_ut_per_unit": NAN3, f"{t}_kept": None, f"{t}_p_value": None})
    return row


ROW_FIELDS = tuple(_blank({"sha256": "", "path": "", "vehicle": "", "vehicle_from": ""}))


def year_to_utc(year: float | None) -> str | None:
    """A decimal year as an ISO 8601 UTC time (to the second)."""
    if year is None or not np.isfinite(year):
        return None
    y = int(year)
    start = _dt.datetime(y, 1, 1, tzinfo=_dt.timezone.utc)
    length = _dt.datetime(y + 1, 1, 1, tzinfo=_dt.timezone.utc) - start
    return (start + (year - y) * length).replace(microsecond=0).isoformat()


def _floats(v, n: int = 3) -> list[float]:
    return NAN3 if v is None else [float(a) for a in np.asarray(v, np.float64).reshape(-1)[:n]]


def _coverage(m: np.ndarray, offset) -> float | None:
    from ...fit.coverage import coverage

    d = np.asarray(m, np.float64) - np.asarray(offset, np.float64)
    norm = np.linalg.norm(d, axis=1)
    ok = norm > 0
    return float(coverage(d[ok] / norm[ok, None])) if np.any(ok) else None


def _fitted(row: dict, d: dict) -> None:
    """The calibration, its σ and the terms of a fit's dict (flight log or recording) into ``row``."""
    c, u = d["calibration"], d["uncertainty"]
    row.update(model=d.get("model"), offset_ut=_floats(c["offset_ut"]), sigma_offset_ut=_floats(u.get("offset_ut")),
               soft_iron=_floats(c["soft_iron"], 9), field_ut=float(c["field_ut"]),
               sigma_field_ut=None if u.get("field_ut") is None else float(u["field_ut"]),
               rms_ut=float(d["rms_ut"]), n_used=int(d["n_used"]))
    for t in d.get("terms", []):
        if t["channel"] in TERMS and "coef_ut_per_unit" in t:
            name = t["channel"]
            row.update({f"{name}_ut_per_unit": _floats(t["coef_ut_per_unit"]),
                        f"sigma_{name}_ut_per_unit": _floats(t["sigma_ut_per_unit"]),
                        f"{name}_kept": bool(t["kept"]), f"{name}_p_value": float(t["p_value"])})


def _failed(row: dict, failure: str, message: str) -> dict:
    return {**row, "status": "failed", "failure": failure, "message": message}


def _log_rows(task: dict, log) -> list[dict]:
    from ...recordings.logs import select
    from ..flightlog import fit_flight_log

    base = _blank(task)
    if log.vehicle_id:
        base.update(vehicle=log.vehicle_id, vehicle_from="log")
    base.update(autopilot=log.autopilot, firmware=log.firmware, flight_year=log.decimal_year,
                flight_time_utc=year_to_utc(log.decimal_year))
    if not log.mags:
        return [_failed(base, "no_magnetometer", f"{task['path']}: the log holds no magnetometer messages")]
    return [_mag_row(task, base, log, i, select, fit_flight_log) for i in _mags_wanted(task, log)]


def _mags_wanted(task: dict, log) -> list[int]:
    mag = task.get("mag")
    return list(range(len(log.mags))) if mag is None else [mag]


def _mag_row(task: dict, base: dict, log, i: int, select, fit_flight_log) -> dict:
    info = log.mags[i] if i < len(log.mags) else None
    row = {**base, "mag_index": i}
    if info is None:
        return _failed(row, "no_such_magnetometer", f"--mag {i}: the log has {len(log.mags)} magnetometers")
    row.update(compass=f"device {info.device_id}" if info.device_id else info.name, device_id=info.device_id,
               external=info.external, mag_name=info.name)
    try:
        lm = select(log, i)
        s = lm.series.only_valid()
        row.update(n_samples=len(lm.series), log_calibration=lm.undone,
                   duration_s=float(s.t_s[-1] - s.t_s[0]) if len(s) > 1 else 0.0)
        d, ok = fit_flight_log(lm, blocks=task.get("blocks", 5))
    except MagcalError as exc:
        return _failed(row, type(exc).__name__, str(exc))
    if not ok:
        return _failed({**row, "mode": d.get("mode")}, str(d["failure"]), str(d["message"]))
    row["mode"] = d["mode"]
    _fitted(row, d)
    row["coverage"] = _coverage(s.field_ut, d["calibration"]["offset_ut"])
    return row


def _recording_rows(task: dict) -> list[dict]:
    from ...fit import fit_calibration
    from ..load import load_series

    row = {**_blank(task), "mag_index": 0, "compass": "recording", "mode": "magnitude"}
    series = load_series(task["path"])
    row["n_samples"] = len(series)
    if len(series) > 1:
        row["duration_s"] = float(series.t_s[-1] - series.t_s[0])
    series, _ = series.thinned(task.get("max_samples", 250_000))
    result = fit_calibration(series, model="auto")
    if not result:
        return [_failed(row, str(result.reason), str(result.message))]
    d = result.to_dict()
    _fitted(row, d)
    row["coverage"] = _coverage(series.field_ut, d["calibration"]["offset_ut"])
    return [row]


def _is_log(path: str) -> bool:
    from ...recordings.logs import HEAD_BYTES, log_kind

    with open(path, "rb") as fh:
        return log_kind(fh.read(HEAD_BYTES)) is not None


def _rows(task: dict) -> list[dict]:
    from ...recordings.logs import read_log

    if _is_log(task["path"]):
        return _log_rows(task, read_log(task["path"]))
    if task.get("mag") is not None:
        return [_failed({**_blank(task), "mag_index": task["mag"]}, "not_a_flight_log",
                        f"{task['path']}: --mag chooses a magnetometer of a flight log; this file is not one")]
    return _recording_rows(task)


def analyse(task: dict) -> dict:
    """``{"key": [sha256, version], "rows": [...]}`` for one task (``path``, ``sha256``,
    ``vehicle``, ``vehicle_from``, ``notes``, optional ``mag``, ``max_samples``, ``blocks``).
    Never raises for the file's sake: a file that cannot be read, or a reader that fails on it,
    is one row whose ``status`` is "unreadable" and whose ``message`` says why."""
    try:
        rows = _rows(task)
    except (MagcalError, OSError) as exc:
        return unreadable(task, type(exc).__name__, str(exc))
    except Exception as exc:  # noqa: BLE001 — a parser's own failure on one file is that file's row
        return unreadable(task, type(exc).__name__, f"{task['path']}: {type(exc).__name__}: {exc}")
    return {"key": [task["sha256"], task.get("version", __version__)], "rows": rows}


def unreadable(task: dict, failure: str, message: str) -> dict:
    """The result of a task whose file could not be analysed at all: one row saying why."""
    row = {**_blank(task), "status": "unreadable", "failure": failure, "message": message}
    return {"key": [task["sha256"], task.get("version", __version__)], "rows": [row]}
