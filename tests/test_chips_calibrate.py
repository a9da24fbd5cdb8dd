"""Each supported chip as a user meets it: the real sketch under the emulator with that chip,
``magcal calibrate`` to written and VERIFIED near the simulated truth, and ``magcal show
--self-test`` inside that part's datasheet window — through the command line, as the README
says."""

from __future__ import annotations

import json

import numpy as np
import pytest
from firmware_support import require_firmware

from magcal.cli import main
from magcal.sim.physics import demo_scenario

CHIPS = {
    "chip=mpu9150": "MPU-9150",
    "chip=mpu9250": "MPU-9250",
    "chip=mpu9250&bits=14": "MPU-9250",
    "chip=icm20948": "ICM-20948",
}


def _json(capsys, *argv) -> tuple[int, dict]:
    code = main(list(argv))
    return code, json.loads(capsys.readouterr().out)


@pytest.mark.slow
@pytest.mark.parametrize("chip", list(CHIPS))
def test_calibrate_writes_and_verifies_and_the_self_test_passes_on_each_chip(tmp_path, capsys, chip):
    require_firmware()
    port = f"emu://?eeprom={tmp_path / 'e.bin'}&{chip}"
    # at 20 Hz the firmware, the physics and the host handle ~750 samples instead of ~1 750 for
    # the same turning; what differs between chips (counts, ASA, resolution, self-test) does not
    # depend on the rate, and the gates still hold the offset to 0.5 µT (1σ) before it is written
    code, done = _json(capsys, "calibrate", "--port", port, "--rate", "20", "--json")
    assert code == 0 and done["status"] == "done", done.get("message")
    assert done["written"] and done["verified"]
    assert done["device"]["chip"].startswith(CHIPS[chip])
    assert ("14-bit" in done["device"]["chip"]) == ("bits=14" in chip)
    truth = demo_scenario(1).physics.truth().offset_ut
    np.testing.assert_allclose(done["calibration"]["offset_ut"], truth, atol=0.5)
    code, shown = _json(capsys, "show", "--port", port, "--self-test", "--json")
    assert code == 0 and shown["self_test"]["passed"]
    for axis in shown["self_test"]["axes"].values():
        lo, hi = axis["window"]
        assert lo <= axis["adjusted"] <= hi
    assert np.allclose(shown["calibration"]["offset_ut"], done["calibration"]["offset_ut"], atol=1e-3)
