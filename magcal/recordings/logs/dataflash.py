"""ArduPilot DataFlash logs (.bin, and the text .log) read with pymavlink's own DFReader.

What is taken, by message (both the old per-instance names and the newer instance field):

=============  ===================================================================
MAG, MAG2…     MagX/Y/Z (mG, body frame, corrected), MOfsX/Y/Z or MOX/Y/Z (the motor
               offset that was added), instance from the name or the ``I`` field
CURR / BAT     ``current_a``, ``vbat_v`` (old CURR in cA/cV as plain integers),
               ``throttle`` (CURR.Throttle 0–1000 → 0–1)
CTUN           ``throttle`` when CURR has none (ThrOut 0–1000 or ThO 0–1)
RCOU           ``motor1…n`` (PWM µs) for the frame's motor count
IMU…, BARO…    ``imu_temp_c``, ``imu2_temp_c``…, ``baro_temp_c``, ``baro2_temp_c``…
ATT            attitude (plus AHRS_TRIM, as the compass sees the board)
GPS            position (fix ≥ 3D) and the date (GPS week and time of week)
PARM, MSG      parameters; firmware and frame
=============  ===================================================================
"""

from __future__ import annotations

import contextlib
import io
import os
import re

import numpy as np

from .conventions import ap_instance_slot, ap_slot_param, describe_device_id, euler_matrix
from .values import FlightLog, MagInfo, Stream

TYPES = ("MAG", "MAG2", "MAG3", "MAG4", "CURR", "BAT", "BAT2", "CTUN", "RCOU", "IMU", "IMU2", "IMU3",
         "BARO", "BAR2", "BAR3", "ATT", "GPS", "PARM", "MSG")
BASE = {"MAG2": "MAG", "MAG3": "MAG", "MAG4": "MAG", "IMU2": "IMU", "IMU3": "IMU", "BAR2": "BARO",
        "BAR3": "BARO", "BAT2": "BAT"}
INTEGER_CHARS = set("bBhHiI")
MOTORS_BY_FRAME = {"QUAD": 4, "HEXA": 6, "OCTA": 8, "OCTA_QUAD": 8, "Y6": 6, "TRI": 3, "DODECAHEXA": 12,
                   "DECA": 10}
MOTORS_BY_FRAME_CLASS = {1: 4, 2: 6, 3: 8, 4: 8, 5: 6, 7: 3, 12: 12, 14: 10}
GPS_EPOCH_YEAR = 1980.0 + 5.0 / 365.25  # 1980-01-06
SECONDS_PER_YEAR = 365.2425 * 86400.0


def is_dataflash(head: bytes) -> bool:
    return head[:2] == b"\xa3\x95" or head.lstrip()[:4] == b"FMT,"


def _open(path: str, head: bytes):
    from pymavlink import DFReader

    if head[:2] == b"\xa3\x95":
        return DFReader.DFReader_binary(path, zero_time_base=False)
    return DFReader.DFReader_text(path, zero_time_base=False)


def _instance(msg, mtype: str) -> int:
    for f in ("I", "Instance", "Inst"):
        if f in msg._fieldnames:
            return int(getattr(msg, f))
    m = re.search(r"(\d)$", mtype)
    return int(m.group(1)) - 1 if m else 0


def _time_s(msg, base: str) -> float:
    names = msg._fieldnames
    if "TimeUS" in names:
        return getattr(msg, "TimeUS") * 1e-6
    if base == "GPS" and "T" in names:  # old GPS: TimeMS is the GPS time of week, T the boot clock
        return getattr(msg, "T") * 1e-3
    return getattr(msg, "TimeMS") * 1e-3


def _collect(reader, warnings: list[str]) -> dict:
    """{(base type, instance): [message, ...]}, params and MSG texts; stops at damage."""
    rows: dict = {}
    params: dict[str, float] = {}
    texts: list[str] = []
    count = 0
    while True:
        try:
            msg = reader.recv_match(type=list(TYPES))
        except Exception as exc:  # pymavlink raises assorted errors on a damaged tail
            warnings.append(f"the log is damaged after {count} messages ({type(exc).__name__}: {exc}); "
                            "read up to there")
            break
        if msg is None:
            break
        count += 1
        mtype = msg.get_type()
        if mtype == "PARM":
            params[str(msg.Name)] = float(msg.Value)
        elif mtype == "MSG":
            texts.append(str(msg.Message))
        else:
            rows.setdefault((BASE.get(mtype, mtype), _instance(msg, mtype)), []).append(msg)
    return {"rows": rows, "params": params, "texts": texts}


@contextlib.contextmanager
def _silenced():
    """pymavlink reports every bad byte on the process's own stdout/stderr (from its compiled
    indexer too): keep that off the user's terminal while parsing; damage is reported once."""
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        saved = [os.dup(1), os.dup(2)]  # Python's own buffers stay untouched: writes go to the StringIOs
        try:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 1)
                os.dup2(null.fileno(), 2)
                yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


def _cut_short(reader) -> bool:
    """The last message header in the file announces more bytes than the file still holds."""
    tail_start = max(0, reader.data_len - 600)
    tail = bytes(reader.data_map[tail_start:reader.data_len])
    at = tail.rfind(b"\xa3\x95")
    if at < 0 or at + 2 >= len(tail) or tail[at + 2] not in reader.formats:
        return False
    return tail_start + at + reader.formats[tail[at + 2]].len > reader.data_len


def _damage(reader) -> list[str]:
    """Bytes the parser could not place in a message: skipped damage, or a stop before the end."""
    counts, formats = getattr(reader, "counts", None), getattr(reader, "formats", {})
    data_len = getattr(reader, "data_len", None)
    if counts is None or data_len is None:
        return []
    placed = sum(counts[t] * formats[t].len for t in formats if t < len(counts) and counts[t])
    lost = data_len - placed
    if lost <= 528:  # ArduPilot pads the end of a log with up to a page of garbage
        return ["the log ends inside a message (cut short): read up to there"] if _cut_short(reader) else []
    return [f"the log is damaged: {lost} of {data_len} bytes are in no readable message; "
            "read what precedes and follows the damage"]


def _column(msgs, name: str) -> np.ndarray | None:
    if not msgs or name not in msgs[0]._fieldnames:
        return None
    return np.array([float(getattr(m, name)) for m in msgs])


def _is_integer_column(reader, mtype: str, name: str) -> bool:
    fmt = reader.formats.get(reader.name_to_id.get(mtype)) if hasattr(reader, "name_to_id") else None
    if fmt is None or name not in fmt.columns:
        return False
    return fmt.format[fmt.columns.index(name)] in INTEGER_CHARS


def _stream(msgs, base: str, values) -> Stream:
    return Stream(np.array([_time_s(m, base) for m in msgs]), values)


def _scaled(reader, msgs, mtype: str, name: str, integer_scale: float) -> np.ndarray | None:
    """A column in its physical unit: old logs store some as plain integers (cA, cV, ‰)."""
    v = _column(msgs, name)
    if v is not None and _is_integer_column(reader, msgs[0].get_type(), name):
        v = v * integer_scale
    return v


def _power_channels(reader, rows) -> dict[str, Stream]:
    out: dict[str, Stream] = {}
    for key in (("BAT", 0), ("CURR", 0)):
        msgs = rows.get(key)
        if not msgs:
            continue
        cur, volt = _scaled(reader, msgs, key[0], "Curr", 0.01), _scaled(reader, msgs, key[0], "Volt", 0.01)
        if cur is not None and "current_a" not in out:
            out["current_a"] = _stream(msgs, key[0], cur)
        if volt is not None and "vbat_v" not in out:
            out["vbat_v"] = _stream(msgs, key[0], volt)
        thr = _scaled(reader, msgs, key[0], "Throttle", 0.001)
        if thr is not None and "throttle" not in out:
            out["throttle"] = _stream(msgs, key[0], thr)
    ctun = rows.get(("CTUN", 0))
    if ctun and "throttle" not in out:
        for name in ("ThO", "ThrOut"):
            thr = _scaled(reader, ctun, "CTUN", name, 0.001)
            if thr is not None:
                out["throttle"] = _stream(ctun, "CTUN", thr)
                break
    return out


def _motor_count(params: dict, texts: list[str]) -> int:
    for t in texts:
        m = re.match(r"Frame:\s*([A-Z0-9_]+)", t)
        if m and m.group(1) in MOTORS_BY_FRAME:
            return MOTORS_BY_FRAME[m.group(1)]
    return MOTORS_BY_FRAME_CLASS.get(int(params.get("FRAME_CLASS", -1)), 0)


def _motor_channels(reader, rows, n_motors: int) -> dict[str, Stream]:
    msgs = rows.get(("RCOU", 0))
    out: dict[str, Stream] = {}
    if not msgs or not n_motors:
        return out
    for i in range(1, n_motors + 1):
        v = _column(msgs, f"C{i}")
        v = _column(msgs, f"Ch{i}") if v is None else v
        if v is not None:
            out[f"motor{i}"] = _stream(msgs, "RCOU", v)
    return out


def _temperature_channels(reader, rows) -> dict[str, Stream]:
    out: dict[str, Stream] = {}
    for base, stem in (("IMU", "imu"), ("BARO", "baro")):
        for (b, inst), msgs in sorted(rows.items()):
            if b != base:
                continue
            v = _scaled(reader, msgs, msgs[0].get_type(), "Temp", 0.01)
            v = _column(msgs, "T") if v is None and base == "IMU" else v
            if v is not None and np.any(v != 0):
                out[f"{stem}{'' if inst == 0 else inst + 1}_temp_c"] = _stream(msgs, base, v)
    return out


def _attitude(rows, params) -> Stream | None:
    msgs = rows.get(("ATT", 0))
    if not msgs:
        return None
    trim = [params.get(f"AHRS_TRIM_{a}", 0.0) for a in "XYZ"]
    roll = np.radians(_column(msgs, "Roll")) + trim[0]
    pitch = np.radians(_column(msgs, "Pitch")) + trim[1]
    yaw = np.radians(_column(msgs, "Yaw")) + trim[2]
    return _stream(msgs, "ATT", euler_matrix(roll, pitch, yaw))


def _position_and_date(rows) -> tuple[Stream | None, float | None]:
    msgs = [m for m in rows.get(("GPS", 0), []) if getattr(m, "Status", 0) >= 3]
    if not msgs:
        return None, None
    pos = np.column_stack([_column(msgs, "Lat"), _column(msgs, "Lng"), _column(msgs, "Alt")])
    week = _column(msgs, "GWk") if "GWk" in msgs[0]._fieldnames else _column(msgs, "Week")
    tow_ms = _column(msgs, "GMS") if "GMS" in msgs[0]._fieldnames else _column(msgs, "TimeMS")
    year = None
    if week is not None and tow_ms is not None and np.median(week) > 0:
        seconds = float(np.median(week)) * 7 * 86400 + float(np.median(tow_ms)) / 1000.0
        year = GPS_EPOCH_YEAR + seconds / SECONDS_PER_YEAR
    return _stream(msgs, "GPS", pos), year


def _mag_info(params, instance: int, name: str, stream: Stream) -> MagInfo:
    dev, slot, how = ap_instance_slot(params, instance)
    ext = None if slot is None else params.get(ap_slot_param("EXTERNAL", slot, params))
    return MagInfo(index=instance, name=name, device_id=dev, device=describe_device_id(dev),
                   external=None if ext is None else bool(ext), samples=len(stream), rate_hz=stream.rate_hz(),
                   calibrated=True, slot=slot, slot_how=how)


def _sample_times(msgs) -> Stream | None:
    """When each MAG sample was taken: newer logs carry it (``S``, the compass's last update on
    the 32-bit microsecond clock) beside the time of writing; older ones only the time of writing."""
    if "S" not in msgs[0]._fieldnames or "TimeUS" not in msgs[0]._fieldnames:
        return None
    written = np.array([int(m.TimeUS) for m in msgs], dtype=np.int64)
    sus = np.array([int(m.S) for m in msgs], dtype=np.int64)
    age = (written - sus) % (1 << 32)
    ok = sus > 0
    return np.where(ok & (age < 1_000_000), written - age, written) * 1e-6


def _mags(reader, rows, params):
    infos, fields, extra = [], [], {}
    keys = sorted(k for k in rows if k[0] == "MAG")
    for key in keys:
        msgs = rows[key]
        xyz = np.column_stack([_column(msgs, f"Mag{a}") for a in "XYZ"])
        t = _sample_times(msgs)
        t = np.array([_time_s(m, "MAG") for m in msgs]) if t is None else t
        stream = Stream(t, xyz)
        name = msgs[0].get_type() if key[1] == 0 or msgs[0].get_type() != "MAG" else f"MAG[{key[1]}]"
        infos.append(_mag_info(params, key[1], name, stream))
        fields.append(stream)
        for stem, what in (("MOfs", "motor_offset"), ("MO", "motor_offset"), ("Ofs", "logged_offset")):
            cols = [_column(msgs, f"{stem}{a}") for a in "XYZ"]
            if all(c is not None for c in cols) and f"{what}{key[1]}" not in extra:
                extra[f"{what}{key[1]}"] = Stream(t, np.column_stack(cols))
    return tuple(infos), tuple(fields), extra


def read(path: str, head: bytes) -> FlightLog:
    """A DataFlash log as a FlightLog; damage ends the reading with a warning, never a traceback."""
    warnings: list[str] = []
    with _silenced():
        reader = _open(path, head)
        got = _collect(reader, warnings)
    warnings += _damage(reader)
    rows, params, texts = got["rows"], got["params"], got["texts"]
    infos, fields, extra = _mags(reader, rows, params)
    channels = {**_power_channels(reader, rows), **_motor_channels(reader, rows, _motor_count(params, texts)),
                **_temperature_channels(reader, rows)}
    position, year = _position_and_date(rows)
    firmware = next((t for t in texts if re.search(r"(Copter|Plane|Rover|Sub|Tracker|Blimp|APM:)", t)), "ArduPilot")
    return FlightLog(path=path, autopilot="ardupilot", firmware=firmware, mags=infos, mag_fields=fields,
                     field_unit_ut=0.1, channels=channels, attitude=_attitude(rows, params), position=position,
                     decimal_year=year, params=params, extra=extra, warnings=tuple(warnings),
                     vehicle_id=_vehicle_id(texts, params))


# ArduPilot writes the board's name and its 96-bit unique id at boot: "CubeOrange 003A0030 3138510B 37343536"
_BOARD_ID = re.compile(r"^(\S+) ([0-9A-Fa-f]{8} [0-9A-Fa-f]{8} [0-9A-Fa-f]{8})$")


def _vehicle_id(texts: list[str], params: dict[str, float]) -> str | None:
    """The board's unique id from its boot line, else a set BRD_SERIAL_NUM; None without either."""
    for t in texts:
        m = _BOARD_ID.match(t.strip())
        if m:
            return f"{m.group(1)} {m.group(2)}"
    serial = params.get("BRD_SERIAL_NUM")
    return f"BRD_SERIAL_NUM {int(serial)}" if serial else None
