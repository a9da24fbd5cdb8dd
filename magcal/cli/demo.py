"""``python -m magcal.cli.demo`` (``make demo``): calibrate the embedded default end to end.

The default is the simulated MPU-9150 (``magcal.sim.physics.demo_scenario``). When the AVR
toolchain and simavr are present, it runs behind the real firmware under the emulator
(``emu://``) and the host talks to it through its real serial backend; otherwise it runs on the
pure-Python board (``sim://``). Either way it says which, then calibrates, writes the result to
the board's EEPROM, reads it back and compares.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile

from . import main as cli_main


def toolchain_present() -> bool:
    return bool(
        shutil.which("avr-gcc")
        and os.path.exists("/usr/include/simavr/sim_avr.h")
        and os.path.isdir("/usr/share/arduino/hardware/arduino/avr")
    )


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    workdir = tempfile.mkdtemp(prefix="magcal-demo-")
    eeprom = os.path.join(workdir, "eeprom.bin")
    if toolchain_present():
        port = f"emu://?seed=1&eeprom={eeprom}"
        print("demo: AVR toolchain found — calibrating the real firmware running under simavr "
              "(emulated MPU-9150 fed by the physics simulator), through the serial backend")
    else:
        port = f"sim://?seed=1&pace=5&eeprom={eeprom}"
        print("demo: no AVR toolchain — calibrating the pure-Python simulated board (sim://); "
              "install gcc-avr, avr-libc, arduino-core-avr, simavr and libsimavr-dev for the firmware route")
    truth = __import__("magcal.sim.physics", fromlist=["demo_scenario"]).demo_scenario(1).physics
    print(f"demo: the simulated board's true hard iron is {list(truth.hard_iron_ut)} µT, "
          f"field {truth.field_ut} µT")
    sys.stdout.flush()
    code = cli_main(["calibrate", "--port", port, *argv])
    shutil.rmtree(workdir, ignore_errors=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
