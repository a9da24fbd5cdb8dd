"""What a flight log reader hands on: streams on the log's own clock, as values.

A reader (``dataflash``, ``ulog``) turns a file into a ``FlightLog``: each magnetometer's field
as logged, the physical channels (``current_a``, ``throttle``, ``motor1``…, ``imu_temp_c``,
``baro_temp_c``, ``vbat_v``), the attitude and the position, the parameters. ``select`` then
picks one magnetometer and puts everything on its timestamps (``LogMag``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ...core.series import Series
from .conventions import ap_numbered_names


@dataclass(frozen=True)
class Stream:
    """One quantity on its own clock: ``t_s`` (n,) seconds since boot, ``values`` (n,) or (n, k)."""

    t_s: np.ndarray
    values: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.t_s, np.float64).reshape(-1)
        v = np.asarray(self.values, np.float64)
        order = np.argsort(t, kind="stable")
        if np.any(np.diff(t) < 0):  # a log can interleave writers; interpolation needs order
            t, v = t[order], v[order]
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "values", v)

    def __len__(self) -> int:
        return len(self.t_s)

    def rate_hz(self) -> float:
        if len(self.t_s) < 2 or self.t_s[-1] <= self.t_s[0]:
            return 0.0
        return float((len(self.t_s) - 1) / (self.t_s[-1] - self.t_s[0]))


@dataclass(frozen=True)
class MagInfo:
    """One magnetometer in a log, in the log's own order (``--mag`` index)."""

    index: int
    name: str  # where it is in the log: "MAG2", "sensor_mag[1]", "vehicle_magnetometer[0]"
    device_id: int | None
    device: str  # the device id decoded: bus, address, type
    external: bool | None
    samples: int
    rate_hz: float
    calibrated: bool  # the log holds the autopilot's corrected field (undone on selection)
    slot: int | None = None  # where the autopilot keeps its calibration (ArduPilot's COMPASS_* slot)
    slot_how: str = ""  # how that slot was found (by device id, or by order in older logs)

    def to_dict(self) -> dict:
        return {"index": self.index, "name": self.name, "device_id": self.device_id, "device": self.device,
                "external": self.external, "samples": self.samples, "rate_hz": round(self.rate_hz, 3),
                "calibrated_in_log": self.calibrated, "slot": self.slot, "slot_how": self.slot_how}

    def describe(self) -> str:
        where = {True: "external", False: "internal", None: "internal/external unknown"}[self.external]
        ident = f"device id {self.device_id} ({self.device})" if self.device_id else "no device id"
        return f"--mag {self.index}: {self.name}, {ident}, {where}, {self.samples} samples at {self.rate_hz:.1f} Hz"


@dataclass(frozen=True)
class FlightLog:
    """A flight log read: streams as logged, nothing resampled or undone yet."""

    path: str
    autopilot: str  # "ardupilot" | "px4"
    firmware: str
    mags: tuple[MagInfo, ...]
    mag_fields: tuple[Stream, ...]  # per magnetometer, (n, 3) in the log's unit (see field_unit_ut)
    field_unit_ut: float  # µT per logged unit: 0.1 for milligauss, 100 for gauss
    channels: Mapping[str, Stream]
    attitude: Stream | None  # (n, 3, 3) body → NED
    position: Stream | None  # (n, 3): latitude °, longitude °, altitude m
    decimal_year: float | None
    params: Mapping[str, float]
    extra: Mapping[str, Stream] = field(default_factory=dict)  # what undoing a calibration needs
    warnings: tuple[str, ...] = ()
    # the vehicle as the log names it: PX4's sys_uuid, ArduPilot's board id (the MSG line of the
    # board name and its 96-bit unique id) or BRD_SERIAL_NUM; None when the log names none
    vehicle_id: str | None = None


@dataclass(frozen=True)
class LogMag:
    """One magnetometer of a log, ready to fit: everything on its timestamps.

    ``series.field_ut`` is the raw field (the log's own calibration undone) in the body frame,
    µT; ``earth_body_ut`` the expected field in the body frame from the log's attitude and the
    World Magnetic Model (None where the log has no attitude or position); ``sensor_to_body`` the
    rotation the autopilot applies after its calibration (needed to write its parameters)."""

    log: FlightLog
    info: MagInfo
    series: Series
    earth_body_ut: np.ndarray | None
    earth_field_ut: float | None
    earth_model: str | None
    sensor_to_body: np.ndarray
    undone: str
    slot: int | None = None  # the autopilot's calibration slot: compass index, CAL_MAGn
    warnings: tuple[str, ...] = ()

    def describe(self) -> dict:
        return {
            "file": self.log.path, "autopilot": self.log.autopilot, "firmware": self.log.firmware,
            "magnetometer": self.info.to_dict(), "undone": self.undone,
            "channels": sorted(self.series.channels), "attitude": self.earth_body_ut is not None,
            "earth_model": self.earth_model, "earth_field_ut": self.earth_field_ut,
            "sensor_to_body": np.asarray(self.sensor_to_body).tolist(), "slot": self.slot,
            "ardupilot_numbered_names": self.log.autopilot == "ardupilot" and ap_numbered_names(self.log.params),
        }
