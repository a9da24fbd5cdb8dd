"""Body-relative guidance (magcal.logic.guidance): the side that is down named from the
accelerometer, the six sides ticked off once turned a full circle, and "you are not moving"
within a few seconds of stillness; boards without an accelerometer keep the field's hint."""

import re

import numpy as np
import pytest

from magcal.logic.guidance import STILL_S, Guide, Nudge, Side, side_down


def _turn(guide, side, t0=0.0, degrees=360.0, steps=40, dip_deg=60.0):
    """The board lies on ``side`` and turns about the vertical: the field's horizontal part
    goes round in the plane across ``side.down``; the accelerometer reads up."""
    d = side.down
    e1 = np.roll(d, 1)
    e2 = np.cross(d, e1)
    dip = np.radians(dip_deg)
    for k in range(steps + 1):
        th = np.radians(degrees) * k / steps
        u = np.cos(dip) * (np.cos(th) * e1 + np.sin(th) * e2) + np.sin(dip) * d
        guide.update(t0 + 0.25 * k, 48.0 * u, accel_g=-d * 1.0 + 0.01 * e1)
    return t0 + 0.25 * steps


def test_the_side_that_is_down_is_named_from_the_accelerometer():
    for side in Side:
        assert side_down(-side.down) is side
        assert side_down(-9.81 * side.down) is side  # any unit
    assert side_down([0.7, 0.0, 0.7]) is None  # on an edge between two sides
    assert side_down([0.0, 0.0, 0.0]) is None


def test_lying_on_a_side_asks_for_a_full_circle_and_ticks_it_off():
    g = Guide()
    _turn(g, Side.LEFT, degrees=120)
    a = g.advice()
    assert a.nudge is Nudge.TURN and a.side is Side.LEFT
    assert "turn it a full circle as it lies on its left side" in a.text and "of 360°" in a.text
    assert "· left" in a.checklist
    _turn(g, Side.LEFT, t0=20.0)
    a = g.advice()
    assert g.done(Side.LEFT) and "✓ left" in a.checklist
    assert a.nudge is Nudge.LAY and a.side is not Side.LEFT and a.text.startswith("lay it ")
    assert "then turn it a full circle" in a.text


def test_a_half_turn_back_and_forth_is_not_a_full_circle():
    g = Guide()
    t = _turn(g, Side.TOP, degrees=150)
    _turn(g, Side.TOP, t0=t, degrees=150)  # and again over the same headings
    assert not g.done(Side.TOP)


def test_every_side_done_says_so():
    g = Guide()
    t = 0.0
    for side in Side:
        t = _turn(g, side, t0=t) + 1
    a = g.advice()
    assert a.nudge is Nudge.DONE and all(f"✓ {s.short}" in a.checklist for s in Side)


def test_holding_still_is_noticed_within_a_few_seconds():
    g = Guide()
    t = _turn(g, Side.RIGHT, degrees=90)
    u = 48.0 * np.array([0.5, 0.0, 0.866])
    for k in range(int(STILL_S / 0.25) + 2):
        g.update(t + 0.25 * k, u + 0.05 * np.sin(k), accel_g=-Side.RIGHT.down)  # noise, no turn
    a = g.advice()
    assert a.still and a.text.startswith("you are not moving: turn it a full circle")
    _turn(g, Side.RIGHT, t0=t + 10, degrees=60)
    assert not g.advice().still


def test_without_an_accelerometer_only_the_stillness_nudge_is_given():
    g = Guide()
    for k in range(20):
        g.update(0.25 * k, [30.0, 10.0 * np.sin(k), 40.0])
    a = g.advice()
    assert a.nudge is Nudge.FIELD_ONLY and a.checklist == "" and not a.still
    for k in range(20):
        g.update(5 + 0.25 * k, [30.0, 0.0, 40.0])
    assert g.advice().still and g.advice().text.startswith("you are not moving")


def test_a_motioncal_board_sends_its_accelerometer_with_each_sample():
    from magcal.devices.motioncal_client import accel_aux
    from magcal.wire import motioncal as mc

    raw = accel_aux(mc.parse_line(b"Raw:0,0,8192,0,0,0,100,200,300"))
    assert raw == {"ax_g": 0.0, "ay_g": 0.0, "az_g": 1.0}
    assert side_down((raw["ax_g"], raw["ay_g"], raw["az_g"])) is Side.BOTTOM
    uni = accel_aux(mc.parse_line(b"Uni:-9.80665,0,0,0,0,0,10,20,30"))
    assert side_down((uni["ax_g"], uni["ay_g"], uni["az_g"])) is Side.RIGHT  # +X down reads −1 g on X


@pytest.mark.slow
def test_calibrate_on_a_still_board_says_you_are_not_moving(tmp_path):
    from test_terminal_width import ESC, _in_terminal

    # (8× real time for 1.5 s: the same 12 s of board time as 4× for 3 s, in half the wait)
    # a board that sends no accelerometer keeps the field-relative hint
    code, out = _in_terminal(["calibrate", "--port", "sim://?pace=8&motion=still&seed=3&accel=off", "--timeout", "1.5"], 80)
    assert code == 3, out[-1500:]
    assert "you are not moving: next: aim the board's" in out and "sides:" not in out
    # one that does is told so in the sides' terms
    code, out = _in_terminal(["calibrate", "--port", "sim://?pace=8&motion=still&seed=3", "--timeout", "1.5"], 80)
    plain = ESC.sub("", out)
    assert code == 3, plain[-1500:]
    assert re.search(r"next: you are not moving: (lay it|turn it a full circle)", plain), plain[-1500:]


@pytest.mark.slow
def test_calibrate_on_the_simulated_board_names_the_sides_from_its_accelerometer():
    from test_terminal_width import ESC, _in_terminal

    # 12 s of board time, as in the test above: too short to calibrate, long enough to be drawn
    code, out = _in_terminal(["calibrate", "--port", "sim://?pace=8&seed=3&eeprom=none", "--timeout", "1.5"], 80)
    plain = ESC.sub("", out)
    assert code == 3, plain[-1500:]
    assert "sides: · flat  · upside down  · left  · right  · front  · back" in plain, plain[-1500:]
    assert re.search(r"next: (lay it|turn it a full circle)", plain)
    assert "next: aim the board's" not in plain


def test_the_simulated_board_sends_the_side_that_is_down():
    """sim:// samples carry the accelerometer (±2 g counts on the wire, g on the sample): the
    reaction to gravity in the magnetometer's body axes (the client turns the wire's IMU axes into them)."""
    from magcal.devices import open_device

    with open_device("sim://?pace=0&eeprom=none&seed=4") as dev:
        dev.open()
        dev.start()
        got = []
        while len(got) < 100:
            got += [s for s in dev.read(0.2) if hasattr(s, "aux")]
        sc = dev.board.scenario
    t = np.array([s.t_s for s in got])
    accel = np.array([[s.aux["ax_g"], s.aux["ay_g"], s.aux["az_g"]] for s in got])
    up = np.einsum("nji,j->ni", sc.orientation(t), [0.0, 0.0, 1.0])
    assert np.allclose(accel, up, atol=0.02)


@pytest.mark.slow
def test_calibrate_on_a_board_that_sends_its_accelerometer_names_the_sides():
    from adafruit_device import AdafruitBoard
    from test_terminal_width import ESC, _in_terminal

    # 300 readings/s, six times the sketch's 50 Hz: its turning is done in ~3 s, a dozen frames
    with AdafruitBoard(cal_period=40, lines_per_s=600, seed=3) as board:
        code, out = _in_terminal(["calibrate", "--port", board.port, "--dialect", "motioncal", "--timeout", "60"], 80)
    plain = ESC.sub("", out)
    assert code == 0, plain[-1500:]
    assert "sides: ✓ flat" in plain or "sides: · flat" in plain, plain[-1500:]
    assert re.search(r"next: (lay it|turn it a full circle)", plain)
    assert "next: aim the board's" not in plain  # the field-relative hint is for boards without one
