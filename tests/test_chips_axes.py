"""The accelerometer's axes against the magnetometer's, per chip (``Chip.mag_from_accel``): the
boards send the IMU's registers in the IMU's axes, the host turns them into the magnetometer's,
and the guide names the side the board lies on in the axes printed on it (the IMU's) while it
reads the field's headings in the magnetometer's."""

import numpy as np
import pytest

from magcal.core.chips import CHIPS, ICM20948, MPU9150, MPU9250_14, MPU9250_16
from magcal.logic.guidance import DONE_BINS, SIDE_COS, Guide, Side, side_down

# the datasheets' orientation figures, written out here on their own: IMU axes from magnetometer axes
_IMU_FROM_MAG = {
    "mpu9150": lambda m: np.array([m[1], m[0], -m[2]]),  # AK8975: mag X = accel Y, Y = accel X, Z = −accel Z
    "mpu9250": lambda m: np.array([m[1], m[0], -m[2]]),  # AK8963: the same turn
    "icm20948": lambda m: np.array([m[0], -m[1], -m[2]]),  # AK09916: X = accel X, Y = −accel Y, Z = −accel Z
}


@pytest.mark.parametrize("chip", CHIPS, ids=lambda c: f"{c.name}-{c.bits}")
def test_the_axis_map_is_the_datasheets_turn_and_round_trips(chip):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(5, 3))
    mag = chip.accel_to_mag(v)
    assert np.array_equal(chip.mag_to_accel(mag), v)
    for i in range(5):
        assert np.array_equal(_IMU_FROM_MAG[chip.name](mag[i]), v[i])
    turn = chip.accel_to_mag(np.eye(3))  # a rotation, not a mirror: the magnetometer stays right-handed
    assert np.isclose(np.linalg.det(turn), 1.0)


def test_the_magnetometer_axes_differ_from_the_accelerometer_on_every_known_chip():
    flat = (0.0, 0.0, 1.0)  # lying components up, the IMU reads +1 g on its Z
    for chip in (MPU9150, MPU9250_14, MPU9250_16, ICM20948):
        assert chip.accel_to_mag(flat).tolist() == [0.0, 0.0, -1.0]
    assert MPU9150.accel_to_mag((1.0, 0.0, 0.0)).tolist() == [0.0, 1.0, 0.0]
    assert ICM20948.accel_to_mag((0.0, 1.0, 0.0)).tolist() == [0.0, -1.0, 0.0]


def _lie_and_turn(guide, chip, side, dip_deg=60.0, steps=40):
    """A real board on ``side`` (printed axes) turned once about the vertical: the IMU reads up
    in its axes, the host hands the guide that reading and the field in the magnetometer's axes."""
    accel_mag = chip.accel_to_mag(-side.down)  # what the sample carries
    down_mag = chip.accel_to_mag(side.down)
    e1 = np.roll(down_mag, 1)
    e2 = np.cross(down_mag, e1)
    dip = np.radians(dip_deg)
    for k in range(steps + 1):
        th = 2 * np.pi * k / steps
        u = np.cos(dip) * (np.cos(th) * e1 + np.sin(th) * e2) + np.sin(dip) * down_mag
        guide.update(0.25 * k, 48.0 * u, accel_mag)


@pytest.mark.parametrize("chip", (MPU9150, MPU9250_16, ICM20948), ids=lambda c: c.name)
def test_a_board_lying_on_a_side_gives_the_guide_that_side_and_a_full_circle_ticks_it(chip):
    for side in Side:
        guide = Guide(chip=chip)
        _lie_and_turn(guide, chip, side)
        assert guide.side is side
        assert len(guide.seen[side]) >= DONE_BINS and guide.done(side)
        assert all(not guide.seen[s] for s in Side if s is not side)


def test_without_the_chip_the_guide_would_name_the_wrong_side():
    """The defect this guards: the magnetometer's axes taken for the printed ones."""
    guide = Guide()
    _lie_and_turn(guide, MPU9150, Side.BOTTOM)
    assert guide.side is Side.TOP  # flat, components up, read as upside down


@pytest.mark.parametrize("chip", ("mpu9150", "mpu9250", "icm20948"))
def test_the_simulated_board_sends_the_imu_axes_and_the_guide_names_the_side_it_lies_on(chip):
    """sim:// puts the physics' gravity (body axes = the magnetometer's) on the wire in the IMU's
    axes; the client turns it back; the guide names the printed side the physics has down."""
    from magcal.devices import open_device

    with open_device(f"sim://?pace=0&eeprom=none&seed=5&chip={chip}") as dev:
        ident = dev.open()
        dev.start()
        got = []
        while len(got) < 60:
            got += [s for s in dev.read(0.2) if hasattr(s, "aux")]
        sc = dev.board.scenario
    guide = Guide(chip=ident.chip)
    decided = 0
    for s in got:
        up_mag = sc.orientation([s.t_s])[0].T @ [0.0, 0.0, 1.0]
        guide.update(s.t_s, s.field_ut, (s.aux["ax_g"], s.aux["ay_g"], s.aux["az_g"]))
        up_imu = _IMU_FROM_MAG[chip](up_mag)
        if np.max(np.abs(up_imu)) > SIDE_COS + 0.02:  # clear of the 35° edge, where noise decides
            want = side_down(up_imu)
            assert guide.side is want
            decided += 1
    assert decided > 0
