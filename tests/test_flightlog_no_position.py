"""A flight log without a position fix: the fit against an Earth field unknown but constant, from
the log's own attitude (``fit.vector.UnknownField``, ``app.flightlog``).

The shipped logs have a GPS fix; taking it away (the log read, its position dropped) gives the
GPS-less log a user would bring, whose positioned fit is the reference: the same samples, the
same attitude, the field from the World Magnetic Model."""

import os
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from logs_extra import need

DATA = os.path.join(os.path.dirname(__file__), "data")
BIN = os.path.join(DATA, "ardupilot_log171_excerpt.bin")
ULG = os.path.join(DATA, "px4_esc_status_excerpt.ulg")


@pytest.fixture(autouse=True)
def _logs_extra():
    need("pymavlink", "pyulog", "pygeomag")


def _both(path, mag):
    """(the log's magnetometer with its position, the same without one)."""
    from magcal.recordings.logs import read_log, select

    log = read_log(path)
    return select(log, mag), select(replace(log, position=None), mag)


def test_without_a_position_the_offset_agrees_with_the_positioned_fit_and_the_size_is_not_claimed():
    from magcal.app.flightlog import attitude_rotations, fit_flight_log

    with_pos, without = _both(BIN, 2)  # MAG3: the motors step and a current term kept
    ref, ok_ref = fit_flight_log(with_pos)
    d, ok = fit_flight_log(without)
    assert ok and ok_ref
    ef = d["earth_field"]
    assert ef["format"] == "magcal.earth_field/1" and ef["mode"] == "unknown_constant"
    assert ref["earth_field"]["mode"] == "model"
    assert not ef["size_determined"] and not ef["declination_determined"]
    assert {"field_size", "declination"} <= set(ef["not_determined"]) and d["uncertainty"]["field_ut"] is None
    assert d["model"] == ref["model"] == "vector+motors_on+current_a"
    delta = np.subtract(d["calibration"]["offset_ut"], ref["calibration"]["offset_ut"])
    assert np.all(np.abs(delta) <= 2.0 * np.array(d["uncertainty"]["offset_ut"])), delta
    # the inclination is pinned by the attitude's tilt: the World Magnetic Model's at the log's place
    ned = np.einsum("nij,nj->ni", attitude_rotations(with_pos), with_pos.earth_body_ut[with_pos.series.valid])
    n, e, down = np.median(ned, axis=0)
    wmm_inc = np.degrees(np.arctan2(down, np.hypot(n, e)))
    assert abs(ef["inclination_deg"] - wmm_inc) <= 3 * ef["sigma_inclination_deg"]


def test_the_terminal_and_the_report_say_what_an_unknown_field_cannot_determine():
    from magcal.app.flightlog import diagnose_flight_log, fit_flight_log
    from magcal.app.report.flightlog import terms_html
    from magcal.cli.fitlog import format_log_diagnosis, format_log_text

    _, without = _both(ULG, 0)
    d, ok = fit_flight_log(without)
    assert ok
    text = format_log_text(d)
    assert "unknown but constant" in text and "Not determined: the field's size" in text
    assert d["earth_field"]["heading_source"] == "magnetometer" and "(EKF2_MAG_TYPE 1)" in text
    diag = diagnose_flight_log(without)
    assert diag["earth_field"]["mode"] == "unknown_constant"
    for words in (format_log_diagnosis(diag), terms_html(diag)):
        assert "no position fix" in words and "declination" in words and "inclination" in words


def test_where_the_heading_came_from_is_read_from_the_parameters_and_changes_the_words():
    from magcal.app.flightlog import earth_field_text, heading_source

    assert heading_source("px4", {"EKF2_AID_MASK": 24, "EKF2_MAG_TYPE": 0})[0] == "external_navigation"
    assert heading_source("px4", {"EKF2_EV_CTRL": 15})[0] == "external_navigation"
    assert heading_source("ardupilot", {"EK3_SRC1_YAW": 1})[0] == "magnetometer"
    assert heading_source("ardupilot", {"EK3_SRC1_YAW": 6})[0] == "external_navigation"
    assert heading_source("px4", {})[0] == "unknown"
    ef = {"mode": "unknown_constant", "inclination_deg": 60.0, "sigma_inclination_deg": 0.2, "size_ut": 50.0,
          "heading_frame_declination_deg": 3.0, "sigma_heading_frame_declination_deg": 0.3}
    by_source = {src: earth_field_text({**ef, "heading_source": src}) for src in ("magnetometer", "external_navigation")}
    assert "the declination the autopilot assumed" in by_source["magnetometer"]
    assert "only if its north is true north" in by_source["external_navigation"]


def test_without_attitude_either_the_fit_says_it_used_the_magnitude_alone():
    from magcal.app.flightlog import fit_flight_log
    from magcal.recordings.logs import read_log, select

    log = read_log(ULG)
    d, ok = fit_flight_log(select(replace(log, position=None, attitude=None), 0))
    assert d["earth_field"]["mode"] == "magnitude_only"
    assert not ok or d["mode"].startswith("magnitude")


def test_a_constant_heading_error_moves_the_declination_and_nothing_else():
    """A heading that came from the magnetometer is off by whatever the autopilot assumed: turning
    every attitude by one yaw angle leaves the calibration unchanged and moves only the fitted
    declination, by that angle — which is why it is not a measurement."""
    from magcal.fit.vector import UnknownField, fit_vector

    rng = np.random.default_rng(3)
    r_nb = Rotation.from_euler("zyx", np.column_stack([rng.uniform(-180, 180, 400), rng.normal(0, 20, 400),
                                                       rng.normal(0, 20, 400)]), degrees=True).as_matrix()
    b_ned, offset = np.array([20.0, 3.0, 45.0]), np.array([12.0, -7.0, 4.0])
    a = np.array([[1.05, 0.02, 0.0], [0.02, 0.97, 0.01], [0.0, 0.01, 0.99]])
    m = np.einsum("ij,nkj,k->ni", a, r_nb, b_ned) + offset + rng.normal(0, 0.3, (400, 3))
    turn = Rotation.from_euler("z", 15, degrees=True).as_matrix()
    fits = [fit_vector(m, {}, UnknownField(r), None, term=None) for r in (r_nb, turn @ r_nb)]
    assert all(fits)
    for f in fits:
        assert np.all(np.abs(f.calibration.offset_ut - offset) <= 3 * f.sigma_offset_ut + 1e-9)
    np.testing.assert_allclose(fits[0].calibration.offset_ut, fits[1].calibration.offset_ut, atol=1e-6)
    dec = [f.earth_field["heading_frame_declination_deg"] for f in fits]
    assert dec[1] - dec[0] == pytest.approx(15.0, abs=1e-4)
    assert fits[0].earth_field["inclination_deg"] == pytest.approx(np.degrees(np.arctan2(45.0, np.hypot(20, 3))), abs=0.5)


def test_magcal_fit_on_a_ulog_written_without_its_gps_topic(tmp_path):
    """As a user brings it: a PX4 log with no GPS topic at all, through ``magcal fit --json``."""
    import json
    import subprocess
    import sys

    from pyulog import ULog

    topics = sorted({d.name for d in ULog(ULG).data_list if "gps" not in d.name})
    path = str(tmp_path / "indoor.ulg")
    ULog(ULG, topics).write_ulog(path)
    r = subprocess.run([sys.executable, "-m", "magcal", "fit", path, "--json"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    fit = json.loads(r.stdout)["fits"][0]
    assert fit["earth_field"]["mode"] == "unknown_constant" and fit["mode"] == "vector"
    assert fit["log"]["earth_model"] is None
