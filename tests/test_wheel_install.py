"""From a wheel in a fresh virtual environment, outside the source tree: the commands a user of
an installed package needs — ``config``, ``service install``, ``firmware build``, ``calibrate``
on the emulated board (real firmware under simavr, built from the packaged sources), ``show``
and ``run`` — work with no source checkout anywhere on the path.

The fresh environment gets the wheel alone (``--no-deps --no-index``); its dependencies (numpy,
scipy, pyserial, pyyaml) are the running environment's, put on its path by a ``.pth`` file, so
the test needs no package index. The running environment's own magcal (an editable install)
is not importable there: a ``.pth`` line adds a folder, not the hooks inside it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from magcal.devices.firmware import toolchain_problem

REPO = Path(__file__).resolve().parents[1]


def _need_toolchain() -> None:
    problem = toolchain_problem(emulator=True)
    if problem is not None:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true but the firmware cannot be built: {problem}")
        pytest.skip(problem)


def _fresh_venv_with_the_wheel(tmp: Path) -> Path:
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(REPO)],
                           capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = (tmp / "dist").glob("magcal_mpu9150-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
    assert "magcal/share/firmware/magcal_mpu9150/magcal_mpu9150.ino" in names
    assert not [n for n in names if n.endswith((".o", ".elf", ".hex", ".so"))]  # sources, not this machine's builds
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    site = Path(subprocess.run([str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    (site / "running_env_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    # --no-compile: the modules the commands below import are compiled when first imported, as
    # they would be; pip need not compile all of them ahead
    inst = subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q", "--ignore-installed",
                           "--no-deps", "--no-index", "--no-compile", str(wheel)], capture_output=True, text=True, timeout=300)
    assert inst.returncode == 0, inst.stderr[-2000:]
    return venv


@pytest.mark.slow
def test_an_installed_wheel_configures_installs_builds_calibrates_shows_and_runs(tmp_path):
    _need_toolchain()
    venv = _fresh_venv_with_the_wheel(tmp_path)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MAGCAL_", "PYTHON", "VIRTUAL_ENV"))}
    env.update(HOME=str(work), XDG_CACHE_HOME=str(work / "cache"), XDG_STATE_HOME=str(work / "state"))
    magcal = str(venv / "bin" / "magcal")

    def run(*args, timeout=300):
        return subprocess.run([magcal, *args], cwd=work, env=env, capture_output=True, text=True, timeout=timeout)

    where = subprocess.run([str(venv / "bin" / "python"), "-c", "import magcal; print(magcal.__file__)"],
                           cwd=work, env=env, capture_output=True, text=True)
    assert where.stdout.startswith(str(venv)), where  # the wheel's copy, not the source tree's

    shown = run("config")
    assert shown.returncode == 0 and shown.stdout == (REPO / "config" / "magcal.yaml").read_text()

    root = tmp_path / "root"
    root.mkdir()
    assert run("service", "install", "--root", str(root)).returncode == 0
    unit = (root / "etc/systemd/system/magcal@.service").read_text()
    assert f"ExecStart={magcal} run --port /dev/%i" in unit
    assert (root / "etc/magcal/magcal.yaml").read_text() == shown.stdout
    assert (root / "usr/share/doc/magcal/service.md").is_file() and (root / "usr/share/doc/magcal/README.md").is_file()

    fw = run("firmware", "build")
    assert fw.returncode == 0, fw.stderr
    hexes = list((work / "cache" / "magcal").glob("firmware-*/build/magcal_mpu9150.hex"))
    assert len(hexes) == 1 and str(hexes[0]) in fw.stdout

    cal = run("calibrate", "--port", "emu://?seed=3", "--json")
    assert cal.returncode == 0 and json.loads(cal.stdout)["verified"], (cal.stderr[-2000:], cal.stdout[-3000:])
    stored = run("show", "--port", "emu://?seed=3", "--json")
    assert stored.returncode == 0 and json.loads(stored.stdout)["calibration"]["offset_ut"] == pytest.approx(
        json.loads(cal.stdout)["calibration"]["offset_ut"], abs=0.01)

    daemon = run("run", "--port", "sim://?pace=0", "--count", "200", "--state-dir", str(work / "daemon"))
    assert daemon.returncode == 0, daemon.stderr[-2000:]
    assert (work / "daemon" / "state.json").is_file()
