"""A fleet of ArduPilot flight logs drawn from a real one, with changes planted at known flights:
the test data of ``magcal fleet`` at any size, made when needed instead of stored.

Every flight is the real ArduCopter flight of ``tests/data/ardupilot_log171_excerpt.bin`` (its
attitude, its battery current, its place; read with magcal's own reader) flown on another day on
another heading (the attitude turned by a random yaw, the current scaled by 0.8–1.2 for another
payload). Each vehicle carries two compasses (an external one and an internal one), each a
``magcal.sim.model.SensorModel`` — the simulator's sensor — with its own hard iron, a small
soft iron, white noise and (internal) a current term; the readings are the simulator's twin of
that flight. What a vehicle's log holds is what ArduPilot 4.x writes (``tests/dataflash_writer``):
the board's id line, COMPASS_* parameters (the log's own calibration, applied to the logged field
as the firmware applies it), ATT, GPS, BAT and MAG per compass. The analysis therefore takes the
path a real log takes: ``read_log``, ``select``, ``fit_flight_log``.

``Plant`` says what changes on a vehicle and from which flight on: a hard-iron step on one compass
(or every compass), or a current term that appears.
"""

from __future__ import annotations

import datetime as dt
import functools
import os
from dataclasses import dataclass, field

import numpy as np

from dataflash_writer import ap4_writer

BASE_LOG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "ardupilot_log171_excerpt.bin")
GPS_EPOCH = dt.datetime(1980, 1, 6)
FIRST_DAY = dt.datetime(2024, 3, 1, 9, 0)
DEVICES = ((97539, True), (590114, False))  # external (I2C), internal (SPI)


@dataclass(frozen=True)
class Plant:
    kind: str = "none"  # "none" | "hard_iron_step" | "current_appears"
    compass: int = 0  # which compass (-1: every compass)
    flight: int = 0  # the first flight with the change
    size: tuple = (0.0, 0.0, 0.0)  # µT (a step) or µT/A (a current term)

    def applies(self, compass: int, flight: int, kind: str) -> bool:
        return self.kind == kind and flight >= self.flight and self.compass in (-1, compass)


@dataclass(frozen=True)
class Vehicle:
    name: str
    seed: int
    flights: int
    noise_ut: float = 1.0
    plant: Plant = field(default_factory=Plant)

    def board_line(self) -> str:
        rng = np.random.default_rng([self.seed, 7])
        return "CubeOrange " + " ".join(f"{int(v):08X}" for v in rng.integers(0, 2 ** 32, 3))

    def compass(self, c: int) -> dict:
        """The truth of compass ``c`` before any change: hard iron (µT), symmetric soft iron,
        current term (µT/A), the log's own offsets (mG, what COMPASS_OFS says)."""
        rng = np.random.default_rng([self.seed, 11, c])
        a = np.eye(3) + np.triu(rng.normal(0, 0.02, (3, 3)))
        current = rng.normal(0, 0.08, 3) if not DEVICES[c][1] else np.zeros(3)
        return {"offset_ut": rng.uniform(-40, 40, 3), "distortion": (a + a.T) / 2, "current_ut_per_a": current,
                "log_ofs_mg": np.round(rng.uniform(-300, 300, 3))}


@functools.lru_cache(maxsize=1)
def base_flight() -> dict:
    """The real flight's times, attitude (body → NED), current and place, on its first compass's clock."""
    from magcal.recordings.logs import read_log, select

    lm = select(read_log(BASE_LOG), 0)
    from magcal.recordings.logs.select import resample_rotations

    t = lm.series.t_s[lm.series.valid]
    return {"t_s": t, "r_nb": resample_rotations(lm.log.attitude, t),
            "current_a": np.asarray(lm.series.channels["current_a"], np.float64)[lm.series.valid],
            "position": np.asarray(lm.log.position.values, np.float64).mean(axis=0)}


def _euler(r):
    """roll, pitch, yaw (rad) of body → NED rotations (Z-Y-X)."""
    return (np.arctan2(r[:, 2, 1], r[:, 2, 2]), -np.arcsin(np.clip(r[:, 2, 0], -1, 1)),
            np.mod(np.arctan2(r[:, 1, 0], r[:, 0, 0]), 2 * np.pi))


def flight_day(j: int) -> dt.datetime:
    return FIRST_DAY + dt.timedelta(days=j, minutes=37 * j)


def _decimal_year(when: dt.datetime) -> float:
    start = dt.datetime(when.year, 1, 1)
    return when.year + (when - start) / (dt.datetime(when.year + 1, 1, 1) - start)


def _readings(v: Vehicle, j: int, c: int, u, t, current) -> np.ndarray:
    """The simulator's twin of compass ``c`` on flight ``j`` (µT, sensor = body frame)."""
    from magcal.core.calibration import Calibration
    from magcal.sim.model import SensorModel

    truth = v.compass(c)
    offset = truth["offset_ut"] + (np.asarray(v.plant.size) if v.plant.applies(c, j, "hard_iron_step") else 0.0)
    k = truth["current_ut_per_a"] + (np.asarray(v.plant.size) if v.plant.applies(c, j, "current_appears") else 0.0)
    size = np.linalg.norm(u, axis=1)  # one place: the same |B| all flight
    cal = Calibration(offset_ut=offset, field_ut=float(size.mean()), soft_iron=np.linalg.inv(truth["distortion"]),
                      coef_ut_per_unit={"current_a": tuple(k)})
    model = SensorModel(calibration=cal, noise_ut=(v.noise_ut,) * 3)
    m, _ = model.simulate(u / size[:, None], t, {"current_a": current}, seed=v.seed * 1000 + j * 10 + c)
    return m


def _params(v: Vehicle) -> dict:
    params = {"COMPASS_MOTCT": 0.0, "AHRS_TRIM_X": 0.0, "AHRS_TRIM_Y": 0.0, "AHRS_TRIM_Z": 0.0}
    for slot, (dev, ext) in enumerate(DEVICES):
        sfx = "" if slot == 0 else str(slot + 1)
        params[f"COMPASS_DEV_ID{sfx}"] = dev
        params["COMPASS_EXTERNAL" if slot == 0 else f"COMPASS_EXTERN{slot + 1}"] = int(ext)
        ofs = v.compass(slot)["log_ofs_mg"]
        for kind, val in (("OFS", ofs), ("DIA", (1.0, 1.0, 1.0)), ("ODI", (0.0, 0.0, 0.0)), ("MOT", (0.0, 0.0, 0.0))):
            params.update({f"COMPASS_{kind}{sfx}_{a}": val[i] for i, a in enumerate("XYZ")})
        params[f"COMPASS_PRIO{slot + 1}_ID"] = dev
    return params


def write_flight(path, v: Vehicle, j: int) -> None:
    """Flight ``j`` of vehicle ``v`` as an ArduPilot 4.x DataFlash log at ``path``."""
    from magcal.recordings.logs.conventions import euler_matrix
    from magcal.recordings.logs.earth import earth_field_ned_ut

    base, rng = base_flight(), np.random.default_rng([v.seed, 3, j])
    t = base["t_s"]
    psi = rng.uniform(0, 2 * np.pi)
    r = np.einsum("ij,njk->nik", euler_matrix(0.0, 0.0, psi), base["r_nb"])
    current = base["current_a"] * rng.uniform(0.8, 1.2)
    when = flight_day(j)
    lat, lon, alt = base["position"]
    ned, _, _ = earth_field_ned_ut([lat], [lon], [alt], _decimal_year(when))
    u = np.einsum("nji,j->ni", r, ned[0])  # the Earth's field in the body frame, µT
    fields = [_readings(v, j, c, u, t, current) for c in range(len(DEVICES))]
    w = ap4_writer()
    w.write("MSG", 1000, "ArduCopter V4.5.7 (2a3dc4b7)")
    w.write("MSG", 1001, v.board_line())
    for name, value in _params(v).items():
        w.write("PARM", 2000, name, value, 0.0)
    _samples(w, v, t, r, current, fields, when, (lat, lon, alt))
    w.save(path)


def _samples(w, v: Vehicle, t, r, current, fields, when, place) -> None:
    roll, pitch, yaw = (np.degrees(a) for a in _euler(r))
    gps = (when - GPS_EPOCH).total_seconds()
    week, tow0 = int(gps // (7 * 86400)), (gps % (7 * 86400)) * 1000.0
    ofs = [v.compass(c)["log_ofs_mg"] for c in range(len(fields))]
    for k, tk in enumerate(t):
        us = int(tk * 1e6)
        w.write("ATT", us, 0, roll[k], 0, pitch[k], 0, yaw[k], 0, 0, 3)
        if k % 2 == 0:
            w.write("GPS", us - 200, 0, 6, int(tow0 + (tk - t[0]) * 1000), week, 14, 0.7, *place, 0, 0, 0, 0, 1)
            w.write("BAT", us - 100, 0, 15.8, 15.9, current[k], 100.0, 5.0, 25.0, 0.01, 80, 1, 100)
        for c, f in enumerate(fields):
            logged = f[k] * 10.0 + ofs[c]  # mG, the log's offsets applied as ArduPilot applies them
            w.write("MAG", us + 1000 + 50 * c, c, *logged, *ofs[c], 0, 0, 0, 1, us % (1 << 32))  # S: when sampled


def fleet(n_vehicles: int, flights: int, seed: int = 0, plants=None, noise_ut: float = 1.0) -> list[Vehicle]:
    """``n_vehicles`` vehicles of ``flights`` flights each; ``plants`` (one per vehicle, or None)."""
    plants = plants or [Plant()] * n_vehicles
    return [Vehicle(f"V{seed:03d}{i:04d}", seed * 100_000 + i + 1, flights, noise_ut, p) for i, p in enumerate(plants)]


def write_fleet(root, vehicles: list[Vehicle]) -> list[str]:
    """Every flight of every vehicle under ``root/<vehicle>/flight_<j>.bin``; the paths, in order."""
    paths = []
    for v in vehicles:
        folder = os.path.join(str(root), v.name)
        os.makedirs(folder, exist_ok=True)
        for j in range(v.flights):
            p = os.path.join(folder, f"flight_{j:03d}.bin")
            write_flight(p, v, j)
            paths.append(p)
    return paths
