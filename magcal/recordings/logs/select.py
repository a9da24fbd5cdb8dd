"""One magnetometer of a FlightLog, ready to fit: the log's own calibration undone, every stream
resampled onto the magnetometer's timestamps, and the expected Earth field in the body frame."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...core.errors import InputError, NeedsChoice
from ...core.series import Series
from . import conventions as cv
from .values import FlightLog, LogMag, MagInfo, Stream


class MagnetometerChoice(NeedsChoice):
    """The log holds several magnetometers and none was chosen; ``mags`` lists them."""

    def __init__(self, path: str, mags: tuple[MagInfo, ...]):
        self.mags = mags
        lines = "\n".join("  " + m.describe() for m in mags)
        super().__init__(f"{path}: the log holds {len(mags)} magnetometers; choose one with --mag N:\n{lines}")


def choose(log: FlightLog, mag: int | None) -> int:
    """The position in ``log.mags`` of --mag N (0-based in the log's order)."""
    if not log.mags:
        raise InputError(f"{log.path}: the log holds no magnetometer data")
    if mag is None:
        if len(log.mags) > 1:
            raise MagnetometerChoice(log.path, log.mags)
        return 0
    for pos, info in enumerate(log.mags):
        if info.index == mag:
            return pos
    raise InputError(f"{log.path}: no magnetometer {mag}; the log has "
                     + ", ".join(str(m.index) for m in log.mags))


def resample(stream: Stream, t_s: np.ndarray) -> np.ndarray:
    """``stream`` linearly interpolated at ``t_s`` (held at its first/last value outside)."""
    v = stream.values.reshape(len(stream), -1)
    out = np.column_stack([np.interp(t_s, stream.t_s, v[:, k]) for k in range(v.shape[1])])
    return out.reshape((len(t_s),) + stream.values.shape[1:])


def resample_rotations(stream: Stream, t_s: np.ndarray) -> np.ndarray:
    """Rotation matrices interpolated element-wise and made orthonormal again (polar factor)."""
    m = resample(stream, t_s)
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _applied_offsets(log: FlightLog, info: MagInfo, comp: cv.ArduPilotCompass, t_s) -> tuple[np.ndarray, str]:
    """The offsets ArduPilot applied: the parameters', unless the offsets it logged with each
    sample (MAG Ofs, whole mG) say otherwise — learnt in flight, or the parameters of another
    compass — in which case the logged ones are taken, sample by sample."""
    logged = log.extra.get(f"logged_offset{info.index}")
    if logged is None:
        return comp.ofs_mg, ""
    got = resample(logged, t_s)
    if np.all(np.abs(got - np.trunc(comp.ofs_mg)) <= 1.0):
        return comp.ofs_mg, ""
    return got, ("; the offsets logged with the samples (MAG Ofs) differ from the parameters' by up to "
                 f"{np.max(np.abs(got - comp.ofs_mg)):.0f} mG, so the logged ones (whole mG) were undone")


def _undo_ardupilot(log: FlightLog, info: MagInfo, field, t_s) -> tuple[np.ndarray, str]:
    if info.slot is None:
        return field, f"nothing: {info.slot_how}, so the field is taken as logged"
    if not any(k.startswith("COMPASS") for k in log.params):
        return field, "nothing: the log holds no COMPASS_* parameters, so the field is taken as logged"
    comp = cv.ap_compass(log.params, info.slot)
    ofs, note = _applied_offsets(log, info, comp, t_s)
    mo = log.extra.get(f"motor_offset{info.index}")
    mo_v = None if mo is None else resample(mo, t_s)
    raw = cv.ap_uncorrect(field, replace(comp, ofs_mg=ofs), mo_v)
    name = lambda kind: cv.ap_param_name(kind, info.slot, None, log.params)  # noqa: E731
    mot = "" if mo_v is None or not np.any(mo_v) else ", the logged motor offset (MOfs) subtracted"
    text = (f"ArduPilot compass slot {info.slot + 1} ({info.slot_how}): raw = M⁻¹(MAG − MOfs)/s − OFS with "
            f"{name('OFS')} = ({', '.join(f'{v:.2f}' for v in comp.ofs_mg)}) mG (added by ArduPilot), M from "
            f"{name('DIA')}/{name('ODI')}, s = {comp.scale:g}{mot}{note}")
    return raw, text


def _undo_px4(log: FlightLog, info: MagInfo, field, t_s) -> tuple[np.ndarray, np.ndarray, str]:
    n = cv.px4_cal_index(log.params, info.device_id)
    if n is None:
        rot = cv.px4_rotation(int(log.params.get("SENS_BOARD_ROT", 0))) if info.external is False else np.eye(3)
        what = "raw sensor_mag" if not info.calibrated else "the logged field (no CAL_MAGn_ID matches it)"
        return field @ rot.T, rot, f"nothing: {what}; rotated into the body frame"
    cal = cv.px4_mag(log.params, n, info.external)
    if not info.calibrated:
        return field @ cal.rotation.T, cal.rotation, (f"nothing (sensor_mag is raw); rotated into the body frame "
                                                      f"as CAL_MAG{n}_ROT/SENS_BOARD_ROT say")
    power, how = None, ""
    if cal.comp_type == 1 and "power_throttle" in log.extra and np.any(cal.comp_ga):
        power, how = resample(log.extra["power_throttle"], t_s), ", throttle compensation"
    elif cal.comp_type in (2, 3) and "current_a" in log.channels and np.any(cal.comp_ga):
        power, how = resample(log.channels["current_a"], t_s) / 1000.0, ", current compensation"
    raw = cv.px4_uncorrect(field, cal, power)
    text = (f"PX4 CAL_MAG{n}: raw = S⁻¹Rᵀ·body + OFF − P·COMP with OFF = ({', '.join(f'{v:.5f}' for v in cal.off_ga)}) "
            f"G, S from CAL_MAG{n}_xSCALE/xODIAG{how}; then rotated back into the body frame")
    return raw @ cal.rotation.T, cal.rotation, text


def _expected(log: FlightLog, t_s) -> tuple[np.ndarray | None, float | None, str | None, list[str]]:
    if log.attitude is None or log.position is None or log.decimal_year is None:
        return None, None, None, []
    from .earth import earth_field_ned_ut

    pos = resample(log.position, t_s)
    ned, model, note = earth_field_ned_ut(pos[:, 0], pos[:, 1], pos[:, 2], log.decimal_year)
    r_nb = resample_rotations(log.attitude, t_s)
    body = np.einsum("nji,nj->ni", r_nb, ned)
    return body, float(np.median(np.linalg.norm(ned, axis=1))), model, [note] if note else []


def select(log: FlightLog, mag: int | None) -> LogMag:
    pos = choose(log, mag)
    info, stream = log.mags[pos], log.mag_fields[pos]
    t = stream.t_s
    field = stream.values
    if log.autopilot == "ardupilot":
        raw, undone = _undo_ardupilot(log, info, field, t)
        rot, slot = np.eye(3), info.slot
    else:
        raw, rot, undone = _undo_px4(log, info, field, t)
        slot = cv.px4_cal_index(log.params, info.device_id)
    channels = {name: resample(s, t) for name, s in log.channels.items() if len(s) >= 2}
    earth, earth_f, model, notes = _expected(log, t)
    field_ut = raw * log.field_unit_ut
    valid = np.all(np.isfinite(field_ut), axis=1)
    source = (f"{log.autopilot} log, {info.describe()}; channels {', '.join(sorted(channels)) or 'none'} resampled "
              f"onto its timestamps; undone: {undone}")
    series = Series(t_s=t, field_ut=np.where(np.isfinite(field_ut), field_ut, 0.0), channels=channels,
                    valid=valid, source=source)
    return LogMag(log=log, info=info, series=series, earth_body_ut=earth, earth_field_ut=earth_f,
                  earth_model=model, sensor_to_body=rot, undone=undone, slot=slot, warnings=tuple(log.warnings) + tuple(notes))
