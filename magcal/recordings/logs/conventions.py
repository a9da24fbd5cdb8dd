"""The autopilots' own conventions, as pure functions: how each corrects a magnetometer, how to
undo that from the parameters in a log, and how a magcal calibration becomes their parameters.

magcal's calibration (``magcal.core.calibration``), body frame, µT::

    h = W (m − b − k·x)          W soft iron, b offset, k per unit of channel x (current, throttle)

ArduPilot (``AP_Compass_Backend::correct_field`` in current ArduPilot, body frame, milligauss)::

    corrected = M · (s · (raw + OFS)) + MOT · x       M from COMPASS_DIA/ODI, s COMPASS_SCALE

so M = W, OFS = −b, MOT = −W·k (and s = 1). COMPASS_MOTCT selects x: 1 throttle (0…1), 2 battery
current (A). Firmware before the motor term moved after the matrix applied it inside
(``M · (raw + OFS + MOT·x)``); the logged MOfs is what was added either way.

PX4 (``calibration::Magnetometer::Correct`` in PX4's sensor_calibration library, gauss)::

    body = R · S · ((raw + P·COMP) − OFF)

with S the symmetric matrix of CAL_MAGn_XSCALE… on the diagonal and CAL_MAGn_XODIAG… off it,
R the rotation of CAL_MAGn_ROT (external) or SENS_BOARD_ROT (internal), P the throttle (0…1) or
the battery current in kA as CAL_MAG_COMP_TYP says. With magcal fitted in the body frame on
m = R·raw: S = Rᵀ W R, OFF = Rᵀ b, COMP = −Rᵀ k (per kA for current). PX4 ≤ 1.10 drivers
applied ``(raw − OFF) · SCALE`` per axis, the same formula with a diagonal S and no COMP.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ...core.calibration import Calibration

MG_PER_UT = 10.0  # 1 µT = 10 mG
GAUSS_PER_UT = 0.01

#: PX4 rotation enum → (roll, pitch, yaw) in degrees (PX4 src/lib/conversion/rotation.h).
PX4_ROTATIONS = {
    0: (0, 0, 0), 1: (0, 0, 45), 2: (0, 0, 90), 3: (0, 0, 135), 4: (0, 0, 180), 5: (0, 0, 225),
    6: (0, 0, 270), 7: (0, 0, 315), 8: (180, 0, 0), 9: (180, 0, 45), 10: (180, 0, 90),
    11: (180, 0, 135), 12: (0, 180, 0), 13: (180, 0, 225), 14: (180, 0, 270), 15: (180, 0, 315),
    16: (90, 0, 0), 17: (90, 0, 45), 18: (90, 0, 90), 19: (90, 0, 135), 20: (270, 0, 0),
    21: (270, 0, 45), 22: (270, 0, 90), 23: (270, 0, 135), 24: (0, 90, 0), 25: (0, 270, 0),
    26: (270, 0, 270), 27: (180, 270, 0), 28: (0, 90, 180), 29: (90, 90, 0), 30: (90, 68, 293),
    31: (270, 90, 0), 32: (0, 9, 180), 33: (0, 45, 0), 34: (0, 315, 0), 35: (90, 0, 270),
    41: (270, 0, 180),
}

BUS_TYPES = {1: "I2C", 2: "SPI", 3: "UAVCAN", 4: "SITL", 5: "MSP", 6: "serial"}


def describe_device_id(dev_id: int | None) -> str:
    """The bus, bus number and address packed in an ArduPilot/PX4 device id (same layout)."""
    if not dev_id:
        return "unknown device"
    dev_id = int(dev_id)
    bus_type, bus, address, devtype = dev_id & 7, (dev_id >> 3) & 31, (dev_id >> 8) & 255, (dev_id >> 16) & 255
    kind = BUS_TYPES.get(bus_type, f"bus type {bus_type}")
    return f"{kind} bus {bus} address 0x{address:02X} devtype 0x{devtype:02X}"


def euler_matrix(roll, pitch, yaw) -> np.ndarray:
    """Body→NED rotation(s) from roll, pitch, yaw in radians (aerospace Z-Y-X order)."""
    r, p, y = (np.asarray(a, np.float64) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    m = np.stack([
        np.stack([cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy], -1),
        np.stack([cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy], -1),
        np.stack([-sp, sr * cp, cr * cp], -1),
    ], -2)
    return m


def px4_rotation(code: int) -> np.ndarray:
    """The 3×3 matrix of a PX4 rotation code (sensor → board/body); ValueError if unknown."""
    if int(code) not in PX4_ROTATIONS:
        raise ValueError(f"PX4 rotation {code} is not one magcal knows")
    r, p, y = np.radians(PX4_ROTATIONS[int(code)])
    return euler_matrix(r, p, y)


def symmetric(diag, offdiag) -> np.ndarray:
    """[[d0, o0, o1], [o0, d1, o2], [o1, o2, d2]] — both autopilots' layout."""
    d, o = np.asarray(diag, np.float64), np.asarray(offdiag, np.float64)
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


# -- ArduPilot --------------------------------------------------------------------------------
@dataclass(frozen=True)
class ArduPilotCompass:
    """One compass's COMPASS_* parameters (milligauss)."""

    ofs_mg: np.ndarray
    matrix: np.ndarray  # from DIA/ODI
    mot_mg: np.ndarray  # per A (MOTCT 2) or per unit throttle (MOTCT 1)
    scale: float
    motct: int


def ap_suffix(index: int) -> str:
    """'' for the first compass, '2', '3' … for the others (COMPASS_OFS2_X)."""
    return "" if index == 0 else str(index + 1)


def ap_param_name(kind: str, index: int, axis: str | None, params: Mapping[str, float]) -> str:
    """COMPASS_OFS2_X, or COMPASS2_OFS_X where a log uses that newer scheme."""
    tail = f"_{axis}" if axis else ""
    if ap_numbered_names(params):
        return f"COMPASS{index + 1}_{kind}{tail}"
    return f"COMPASS_{kind}{ap_suffix(index)}{tail}"


AP_MAX_SLOTS = 3  # COMPASS_MAX_INSTANCES: the slots that carry a calibration


def ap_slot_param(kind: str, slot: int, params: Mapping[str, float]) -> str:
    """A per-slot parameter without axis: COMPASS_DEV_ID2 (or COMPASS2_DEV_ID); EXTERNAL is
    COMPASS_EXTERNAL for the first slot and COMPASS_EXTERN2… for the others in the old scheme."""
    if ap_numbered_names(params):
        return f"COMPASS{slot + 1}_{'EXTERN' if kind == 'EXTERNAL' else kind}"
    if kind == "EXTERNAL":
        return "COMPASS_EXTERNAL" if slot == 0 else f"COMPASS_EXTERN{slot + 1}"
    return f"COMPASS_{kind}{ap_suffix(slot)}"


def ap_instance_slot(params: Mapping[str, float], instance: int) -> tuple[int | None, int | None, str]:
    """(device id, calibration slot, how it was found) of the compass a log writes as MAG
    instance ``instance``.

    ArduPilot keeps the calibration (COMPASS_OFS/DIA/ODI/MOT/SCALE/ORIENT/EXTERNAL and the
    DEV_ID it belongs to) per *slot*, but since the compass priority list (COMPASS_PRIOn_ID)
    its frontend — and the MAG log message, written by ``Compass::Write_Compass_instance`` for
    each priority — numbers the compasses by *priority*: MAG instance i is the device whose id is
    COMPASS_PRIO(i+1)_ID, and its calibration is the slot whose COMPASS_DEV_ID holds that id
    (``Compass::_get_state_id``). A log without the priority parameters (before that change)
    numbers both the same way. The slot is None when no slot holds the device's id."""
    prio = params.get(f"COMPASS_PRIO{instance + 1}_ID")
    if prio is None:
        dev = params.get(ap_slot_param("DEV_ID", instance, params))
        return (int(dev) if dev else None), instance, "the log has no COMPASS_PRIOn_ID: MAG instance = slot"
    dev = int(prio)
    for slot in range(AP_MAX_SLOTS):
        if dev and int(params.get(ap_slot_param("DEV_ID", slot, params), 0)) == dev:
            return dev, slot, (f"COMPASS_PRIO{instance + 1}_ID = {dev} is {ap_slot_param('DEV_ID', slot, params)}: "
                               f"slot {slot + 1}")
    return (dev or None), None, f"COMPASS_PRIO{instance + 1}_ID = {dev} matches no COMPASS_DEV_ID slot"


def ap_compass(params: Mapping[str, float], index: int) -> ArduPilotCompass:
    def vec(kind, default):
        return np.array([params.get(ap_param_name(kind, index, a, params), default) for a in "XYZ"], float)

    dia = vec("DIA", 1.0)
    if not np.any(dia):
        dia = np.ones(3)  # ArduPilot treats all-zero diagonals as unset
    scale = float(params.get(ap_param_name("SCALE", index, None, params), 1.0) or 1.0)
    if not 0.1 < scale < 10:  # ArduPilot ignores a scale factor outside its sanity range
        scale = 1.0
    return ArduPilotCompass(vec("OFS", 0.0), symmetric(dia, vec("ODI", 0.0)), vec("MOT", 0.0), scale,
                            int(params.get("COMPASS_MOTCT", 0)))


def ap_correct(raw_mg, c: ArduPilotCompass, x=None) -> np.ndarray:
    """ArduPilot's correction of body-frame raw fields (n, 3) mG; x the throttle or current."""
    raw = np.atleast_2d(np.asarray(raw_mg, np.float64))
    out = (c.scale * (raw + c.ofs_mg)) @ c.matrix.T
    if c.motct in (1, 2) and x is not None:
        out = out + np.outer(np.asarray(x, np.float64).reshape(-1), c.mot_mg)
    return out


def ap_uncorrect(corrected_mg, c: ArduPilotCompass, motor_offset_mg=None) -> np.ndarray:
    """Raw body-frame field from ArduPilot's corrected one and the motor offset it added (MOfs)."""
    v = np.atleast_2d(np.asarray(corrected_mg, np.float64))
    if motor_offset_mg is not None:
        v = v - np.atleast_2d(motor_offset_mg)
    return np.linalg.solve(c.matrix, v.T).T / c.scale - c.ofs_mg


def _param_block(name, offset, matrix, comp) -> dict[str, float]:
    """The four groups both autopilots write, each X, Y, Z: offsets, the matrix's diagonal, its
    off-diagonal (xy, xz, yz) and the interference term; ``name(kind, axis)`` names them."""
    out = {name("OFS", a): float(offset[i]) for i, a in enumerate("XYZ")}
    out.update({name("DIA", a): float(matrix[i, i]) for i, a in enumerate("XYZ")})
    out.update({name("ODI", a): float(matrix[r, c]) for a, (r, c) in zip("XYZ", ((0, 1), (0, 2), (1, 2)))})
    out.update({name("MOT", a): float(comp[i]) for i, a in enumerate("XYZ")})
    return out


def to_ardupilot(cal: Calibration, index: int, term: str | None, numbered: bool = False) -> dict[str, float]:
    """COMPASS_* parameters (mG) that make ArduPilot apply ``cal`` (fitted in the body frame);
    ``numbered`` writes the newer per-compass names (COMPASS2_OFS_X for COMPASS_OFS2_X)."""
    w, b = cal.soft_iron, cal.offset_ut
    k = cal.coef_ut_per_unit.get(term, np.zeros(3)) if term else np.zeros(3)
    ofs, mot = -b * MG_PER_UT, -(w @ k) * MG_PER_UT
    ofs, mot = ofs + 0.0, mot + 0.0  # no "-0" in the file
    sfx = ap_suffix(index)
    if numbered:
        out = _param_block(lambda kind, a: f"COMPASS{index + 1}_{kind}_{a}", ofs, w, mot)
        out[f"COMPASS{index + 1}_SCALE"] = 1.0
    else:
        out = _param_block(lambda kind, a: f"COMPASS_{kind}{sfx}_{a}", ofs, w, mot)
        out[f"COMPASS_SCALE{sfx}"] = 1.0
    if term:
        out["COMPASS_MOTCT"] = 2.0 if term == "current_a" else 1.0
    return out


def ap_numbered_names(params: Mapping[str, float]) -> bool:
    """True when a log's parameters use the newer per-compass names (COMPASS1_OFS_X …)."""
    return "COMPASS1_OFS_X" in params and "COMPASS_OFS_X" not in params


# -- PX4 --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Px4Mag:
    """One CAL_MAGn_* calibration (gauss) and the rotation PX4 applies after it."""

    index: int
    off_ga: np.ndarray
    scale: np.ndarray  # symmetric S
    comp_ga: np.ndarray  # per unit of power (throttle, or kA)
    rotation: np.ndarray  # sensor → body
    comp_type: int


def px4_cal_index(params: Mapping[str, float], device_id: int | None) -> int | None:
    """n of the CAL_MAGn_ID equal to ``device_id`` (the prime magnetometer's when None)."""
    want = device_id if device_id else params.get("CAL_MAG_PRIME")
    for n in range(8):
        if f"CAL_MAG{n}_ID" in params and want and int(params[f"CAL_MAG{n}_ID"]) == int(want):
            return n
    return None


def px4_mag(params: Mapping[str, float], n: int, external: bool | None = None) -> Px4Mag:
    def vec(kind, default):
        return np.array([params.get(f"CAL_MAG{n}_{a}{kind}", default) for a in "XYZ"], float)

    rot = int(params.get(f"CAL_MAG{n}_ROT", -1))
    if external is False or rot < 0:
        rot = int(params.get("SENS_BOARD_ROT", 0))
    return Px4Mag(n, vec("OFF", 0.0), symmetric(vec("SCALE", 1.0), vec("ODIAG", 0.0)), vec("COMP", 0.0),
                  px4_rotation(rot), int(params.get("CAL_MAG_COMP_TYP", 0)))


def px4_uncorrect(body_ga, c: Px4Mag, power=None) -> np.ndarray:
    """Raw sensor fields (gauss) from PX4's corrected body-frame ones."""
    v = np.atleast_2d(np.asarray(body_ga, np.float64)) @ c.rotation
    raw = np.linalg.solve(c.scale, v.T).T + c.off_ga
    if power is not None:
        raw = raw - np.outer(np.asarray(power, np.float64).reshape(-1), c.comp_ga)
    return raw


def to_px4(cal: Calibration, n: int, sensor_to_body, term: str | None) -> dict[str, float]:
    """CAL_MAGn_* (gauss) that make PX4 apply ``cal`` (fitted in the body frame on R·raw)."""
    r = np.asarray(sensor_to_body, np.float64).reshape(3, 3)
    s = r.T @ cal.soft_iron @ r
    off = r.T @ cal.offset_ut * GAUSS_PER_UT
    k = cal.coef_ut_per_unit.get(term, np.zeros(3)) if term else np.zeros(3)
    comp = -(r.T @ k) * GAUSS_PER_UT * (1000.0 if term == "current_a" else 1.0) + 0.0
    px4_kind = {"OFS": "OFF", "DIA": "SCALE", "ODI": "ODIAG", "MOT": "COMP"}
    out = _param_block(lambda kind, a: f"CAL_MAG{n}_{a}{px4_kind[kind]}", off, s, comp)
    out["CAL_MAG_COMP_TYP"] = float({None: 0, "current_a": 2}.get(term, 1))
    return out


INTEGER_PARAMS = ("COMPASS_MOTCT", "CAL_MAG_COMP_TYP")


def format_params(params: Mapping[str, float], header: list[str], qgc: bool = False) -> str:
    """A parameter file: '# ' comment lines, then ``NAME VALUE`` (MAVProxy and Mission Planner
    read it), or with ``qgc`` QGroundControl's ``1<TAB>1<TAB>NAME<TAB>VALUE<TAB>TYPE`` lines
    (type 6 int32, 9 float32) that its Load from file takes for PX4."""
    lines = [f"# {h}" for h in header]
    for k, v in params.items():
        is_int = k in INTEGER_PARAMS
        text = str(int(v)) if is_int else f"{v:.9g}"
        lines.append(f"1\t1\t{k}\t{text}\t{6 if is_int else 9}" if qgc else f"{k} {text}")
    return "\n".join(lines) + "\n"


def parse_params(text: str) -> dict[str, float]:
    """The NAME → value of a file written by format_params (either layout, or NAME,VALUE)."""
    out = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        name, value = (parts[2], parts[3]) if len(parts) == 5 else (parts[0], parts[1])
        out[name] = float(value)
    return out
