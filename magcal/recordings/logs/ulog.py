"""PX4 ULog files (.ulg) read with pyulog.

Magnetometers: each ``sensor_mag`` instance (raw, per device, the driver's rotation applied), or
where the log has none each ``vehicle_magnetometer`` instance (calibrated by CAL_MAGn_*, body
frame; undone on selection). Channels: ``current_a`` and ``vbat_v`` (battery_status),
``throttle`` (actuator_controls_0 control[3], or −vehicle_thrust_setpoint z), ``motor1…n``
(actuator_motors, else the busiest actuator_outputs instance), ``esc1_current_a…`` (esc_status),
``imu_temp_c`` (sensor_accel, vehicle_imu_status), ``baro_temp_c`` (vehicle_air_data,
sensor_baro). Attitude from vehicle_attitude; position and date from the GPS topic.
"""

from __future__ import annotations

import numpy as np

from .conventions import describe_device_id
from .values import FlightLog, MagInfo, Stream

TOPICS = ["sensor_mag", "vehicle_magnetometer", "battery_status", "actuator_controls_0", "vehicle_thrust_setpoint",
          "actuator_motors", "actuator_outputs", "esc_status", "sensor_accel", "vehicle_imu_status",
          "vehicle_air_data", "sensor_baro", "vehicle_attitude", "vehicle_gps_position", "sensor_gps"]
UNIX_EPOCH_YEAR = 1970.0
SECONDS_PER_YEAR = 365.2425 * 86400.0
ULOG_MAGIC = b"ULog\x01\x12\x35"


def is_ulog(head: bytes) -> bool:
    return head[:7] == ULOG_MAGIC


def _topics(ulog) -> dict:
    """{(name, multi_id): data dict} sorted by instance."""
    return {(d.name, d.multi_id): d.data for d in sorted(ulog.data_list, key=lambda d: (d.name, d.multi_id))}


def _t(data) -> np.ndarray:
    return np.asarray(data["timestamp"], np.float64) * 1e-6


def _first(topics, name: str, fields: tuple[str, ...], scale: float = 1.0) -> Stream | None:
    for (n, _), data in topics.items():
        if n != name:
            continue
        for f in fields:
            if f in data:
                v = np.asarray(data[f], np.float64) * scale
                if np.any(np.isfinite(v) & (v != 0)):
                    return Stream(_t(data), v)
    return None


def _mag_streams(topics, params) -> list[dict]:
    """Every magnetometer stream: raw sensor_mag and calibrated vehicle_magnetometer instances."""
    out = []
    for (name, multi), data in topics.items():
        if name not in ("sensor_mag", "vehicle_magnetometer"):
            continue
        cols = ["x", "y", "z"] if "x" in data else [f"magnetometer_ga[{i}]" for i in range(3)]
        dev = int(data["device_id"][0]) if "device_id" in data else None
        if dev is None and name == "vehicle_magnetometer" and multi == 0:
            dev = int(params.get("CAL_MAG_PRIME", 0)) or None  # older logs: the voted primary only
        out.append({"name": f"{name}[{multi}]", "raw": name == "sensor_mag", "device_id": dev,
                    "external": bool(data["is_external"][0]) if "is_external" in data else None,
                    "stream": Stream(_t(data), np.column_stack([np.asarray(data[c], np.float64) for c in cols]))})
    return out


def _mags(topics, params):
    """One entry per magnetometer, in the log's order (sensor_mag instances first): the raw
    stream, or the calibrated one where that was logged more often (PX4's default logging keeps
    sensor_mag at about 1 Hz and vehicle_magnetometer faster)."""
    streams = _mag_streams(topics, params)
    chosen: dict = {}
    for st in streams:  # sensor_mag sorts before vehicle_magnetometer
        key = st["device_id"] if st["device_id"] else st["name"]
        best = chosen.get(key)
        if best is None or len(st["stream"]) > len(best["stream"]):
            if best is not None and st["external"] is None:
                st = {**st, "external": best["external"]}
            chosen[key] = st
    infos, fields = [], []
    for index, st in enumerate(chosen.values()):
        dev, ext = st["device_id"], st["external"]
        ext = _external_from_params(params, dev) if ext is None else ext
        infos.append(MagInfo(index=index, name=st["name"], device_id=dev, device=describe_device_id(dev),
                             external=ext, samples=len(st["stream"]), rate_hz=st["stream"].rate_hz(),
                             calibrated=not st["raw"]))
        fields.append(st["stream"])
    return tuple(infos), tuple(fields)


def _external_from_params(params, dev) -> bool | None:
    """Older PX4: CAL_MAGn_ROT is −1 for an internal magnetometer, a rotation for an external one."""
    for n in range(8):
        if dev and int(params.get(f"CAL_MAG{n}_ID", 0)) == dev and f"CAL_MAG{n}_ROT" in params:
            return int(params[f"CAL_MAG{n}_ROT"]) >= 0
    return None


def _motors(topics) -> dict[str, Stream]:
    out: dict[str, Stream] = {}
    for (name, _), data in topics.items():
        if name == "actuator_motors":
            for i in range(12):
                v = np.asarray(data.get(f"control[{i}]", []), np.float64)
                if len(v) and np.any(np.isfinite(v)) and np.nanstd(v) > 0:
                    out[f"motor{i + 1}"] = Stream(_t(data), v)
            return out
    best, score = None, 0.0
    for (name, _), data in topics.items():
        if name == "actuator_outputs":
            n = int(np.max(data.get("noutputs", [0])))
            s = sum(float(np.nanstd(data[f"output[{i}]"])) for i in range(n) if f"output[{i}]" in data)
            best, score = (data, n) if s > score else best, max(score, s)
    if best is not None:
        data, n = best
        for i in range(n):
            v = np.asarray(data[f"output[{i}]"], np.float64)
            if np.nanstd(v) > 0:
                out[f"motor{len(out) + 1}"] = Stream(_t(data), v)
    return out


def _escs(topics) -> dict[str, Stream]:
    data = topics.get(("esc_status", 0))
    out: dict[str, Stream] = {}
    if data is None:
        return out
    for i in range(8):
        key = f"esc[{i}].esc_current"
        if key in data and np.any(np.asarray(data[key]) != 0):
            out[f"esc{i + 1}_current_a"] = Stream(_t(data), np.asarray(data[key], np.float64))
    return out


def _channels(topics) -> dict[str, Stream]:
    found = {
        "current_a": _first(topics, "battery_status", ("current_a",)),
        "vbat_v": _first(topics, "battery_status", ("voltage_v",)),
        "throttle": _first(topics, "actuator_controls_0", ("control[3]",))
        or _first(topics, "vehicle_thrust_setpoint", ("xyz[2]",), -1.0),
        "imu_temp_c": _first(topics, "sensor_accel", ("temperature",))
        or _first(topics, "vehicle_imu_status", ("temperature_accel",)),
        "baro_temp_c": _first(topics, "vehicle_air_data", ("baro_temp_celcius",))
        or _first(topics, "sensor_baro", ("temperature",)),
    }
    cur = found["current_a"]
    if cur is not None and not np.any(cur.values > 0):  # −1: not measured
        found["current_a"] = None
    out = {k: v for k, v in found.items() if v is not None}
    return {**out, **_motors(topics), **_escs(topics)}


def _attitude(topics) -> Stream | None:
    data = topics.get(("vehicle_attitude", 0))
    if data is None or "q[0]" not in data:
        return None
    w, x, y, z = (np.asarray(data[f"q[{i}]"], np.float64) for i in range(4))
    m = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
    return Stream(_t(data), m)


def _position_and_date(topics, ulog) -> tuple[Stream | None, float | None]:
    for name in ("vehicle_gps_position", "sensor_gps"):
        data = topics.get((name, 0))
        if data is None:
            continue
        ok = np.asarray(data.get("fix_type", np.full(len(data["timestamp"]), 3))) >= 3
        if not ok.any():
            continue
        if "latitude_deg" in data:
            lat, lon, alt = data["latitude_deg"], data["longitude_deg"], data["altitude_msl_m"]
        else:
            lat, lon, alt = data["lat"] * 1e-7, data["lon"] * 1e-7, data["alt"] * 1e-3
        pos = np.column_stack([lat, lon, alt]).astype(np.float64)[ok]
        utc = np.asarray(data.get("time_utc_usec", [0]), np.float64)
        year = UNIX_EPOCH_YEAR + np.median(utc[utc > 0]) * 1e-6 / SECONDS_PER_YEAR if np.any(utc > 0) else None
        return Stream(_t(data)[ok], pos), year
    return None, None


def _ends_inside_a_message(path: str) -> bool:
    """Walk the message frames (u16 size, u8 type, payload) after the 16-byte file header: a
    log cut short (a battery pulled, a copy interrupted) ends inside its last message."""
    with open(path, "rb") as fh:
        data = fh.read()
    pos = 16
    while pos + 3 <= len(data):
        pos += 3 + int.from_bytes(data[pos:pos + 2], "little")
    return pos != len(data)


def read(path: str) -> FlightLog:
    """A ULog as a FlightLog; pyulog reads up to damage (then the log says so in warnings)."""
    from pyulog import ULog

    ulog = ULog(path, TOPICS, disable_str_exceptions=True)
    warnings = []
    if getattr(ulog, "file_corruption", False):
        warnings.append("the log is damaged; pyulog read what it could up to and around the damage")
    elif _ends_inside_a_message(path):
        warnings.append("the log ends inside a message (cut short): read up to there")
    params = {k: float(v) for k, v in ulog.initial_parameters.items()}
    topics = _topics(ulog)
    infos, fields = _mags(topics, params)
    position, year = _position_and_date(topics, ulog)
    info = ulog.msg_info_dict
    firmware = f"PX4 {info.get('ver_sw_branch', '')} {info.get('ver_sw', '')[:8]} on {info.get('ver_hw', '?')}".strip()
    extra = {}
    if (thr := _first(topics, "actuator_controls_0", ("control[3]",))) is not None:
        extra["power_throttle"] = thr
    return FlightLog(path=path, autopilot="px4", firmware=firmware, mags=infos, mag_fields=fields,
                     field_unit_ut=100.0, channels=_channels(topics), attitude=_attitude(topics),
                     position=position, decimal_year=year, params=params, extra=extra, warnings=tuple(warnings),
                     vehicle_id=str(info.get("sys_uuid", "")).strip() or None)
