"""Channels that follow the board's orientation or the magnetic reading are left out of the
diagnosis candidates, by name and by test, each with a line saying why; --channels overrides."""

from __future__ import annotations

import numpy as np
import pytest

from magcal.cli import main
from magcal.core.series import Series
from magcal.diagnose import diagnose
from magcal.diagnose.hygiene import kind_by_name, tokens
from magcal.recordings.table import save_csv
from magcal.sim.physics import Motion, Physics, Scenario, Temperature

HARD = (21.0, -33.0, 8.0)
SOFT = ((1.015, 0.004, 0.0), (0.004, 0.99, 0.003), (0.0, 0.003, 0.995))
TEMP_COEF = (0.08, -0.05, 0.04)


def _imu(sc: Scenario, t: np.ndarray) -> dict:
    """What an IMU on the same board would log: gravity in the body frame (g), body rates
    (deg/s), attitude angles (deg) and a quaternion — all functions of the orientation."""
    r = sc.orientation(t)
    acc = np.einsum("nji,j->ni", r, np.array([0.0, 0.0, 1.0]))
    dt = 1e-3
    dr = (sc.orientation(t + dt) - r) / dt
    w = np.einsum("nji,njk->nik", r, dr)  # Rᵀ Ṙ = [ω]×
    gyro = np.degrees(np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=1))
    pitch = np.degrees(np.arcsin(np.clip(-r[:, 2, 0], -1, 1)))
    roll = np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2]))
    qw = 0.5 * np.sqrt(np.maximum(1 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2], 1e-12))
    return {"acc": acc, "gyro": gyro, "pitch": pitch, "roll": roll, "qw": qw}


@pytest.fixture(scope="module")
def board():
    sc = Scenario(physics=Physics(hard_iron_ut=HARD, distortion=SOFT, temp_coef_ut_per_c=TEMP_COEF),
                  motion=Motion("sphere", period_s=20.0), temperature=Temperature(swing_c=20.0, period_s=60.0), seed=171)
    run = sc.simulate(5000, 50.0)
    s = run.series
    return sc, s, _imu(sc, s.t_s)


@pytest.mark.slow
def test_named_orientation_and_reading_channels_are_left_out_and_the_real_effect_found(board):
    sc, s, imu = board
    chans = {"temp_c": s.channels["temp_c"], "acc_x_g": imu["acc"][:, 0], "acc_y_g": imu["acc"][:, 1],
             "gyro_z_dps": imu["gyro"][:, 2], "roll": imu["roll"], "q0": imu["qw"],
             "mag_x_counts": np.round(s.field_ut[:, 0] / 0.3), "fc_bias_est_x": np.cumsum(np.ones(len(s.t_s))) % 97}
    d = diagnose(Series(t_s=s.t_s, field_ut=s.field_ut, channels=chans))
    assert sorted(d.effects) == ["soft_iron", "temperature_drift"]
    left = {x["channel"]: x["reason"] for x in d.to_dict()["limits"] if x.get("left_out")}
    assert set(left) == set(chans) - {"temp_c"}
    assert "accelerometer" in left["acc_x_g"] and "gyro" in left["gyro_z_dps"] and "magnetometer" in left["mag_x_counts"]
    assert "estimator" in left["fc_bias_est_x"] and "quaternion" in left["q0"] and "attitude" in left["roll"]


@pytest.mark.slow
def test_unnamed_orientation_channels_are_recognised_by_test(board):
    sc, s, imu = board
    slow = 12.0 - 0.5 * (s.t_s / s.t_s[-1]) + 0.01 * np.sin(s.t_s / 7.0)  # a battery voltage: kept
    chans = {"col4": imu["acc"][:, 0], "col5": imu["acc"][:, 2], "col16": imu["pitch"], "col20": slow}
    d = diagnose(Series(t_s=s.t_s, field_ut=s.field_ut, channels=chans))
    left = {x["channel"]: x for x in d.to_dict()["limits"] if x.get("left_out")}
    assert set(left) == {"col4", "col5", "col16"}
    assert all(x["orientation_share"] >= 0.5 and "follows the board's orientation" in x["reason"] for x in left.values())
    assert "covariate:col20" not in d.effects


@pytest.mark.slow
def test_naming_the_channels_tests_them_anyway(board, tmp_path, capsys):
    sc, s, imu = board
    path = tmp_path / "imu.csv"
    save_csv(Series(t_s=s.t_s, field_ut=s.field_ut, channels={"temp_c": s.channels["temp_c"], "acc_x_g": imu["acc"][:, 0]}), path)
    assert main(["diagnose", str(path)]) == 0
    out = capsys.readouterr().out
    assert "left out    acc_x_g: an accelerometer" in out and "--channels to test them" in out
    assert main(["diagnose", str(path), "--json", "--channels", "temp_c,acc_x_g"]) == 0
    out = capsys.readouterr().out
    assert '"left_out"' not in out and "temperature_drift" in out


@pytest.mark.parametrize("name,kind", [
    ("mag_x_counts", "magnetometer"), ("magX", "magnetometer"), ("imu_mx", "magnetometer"), ("rm3100_x", "magnetometer"),
    ("acc_x_g", "accelerometer"), ("imu_az", "accelerometer"), ("accel_Y", "accelerometer"),
    ("gyro_roll", "gyro"), ("imu_gx", "gyro"), ("pitch", "attitude"), ("gps_headingNc", "attitude"),
    ("xbee_qw", "quaternion"), ("fc_bias_est_z", "estimator"),
    ("temp_c", ""), ("vbat_V", ""), ("current_A", ""), ("rc_throttle", ""), ("enviro_h", ""),
])
def test_kinds_by_name(name, kind):
    assert (kind in kind_by_name(name)) if kind else kind_by_name(name) == ""


def test_tokens_split_words_and_camel_case():
    assert tokens("fc_bias_est_x") == ["fc", "bias", "est", "x"]
    assert tokens("gps_headingNc") == ["gps", "heading", "nc"]
