"""What an installer and an operator meet: the license, the package metadata, the service
unit's documentation and its log lines."""

import os
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_the_license_file_is_the_mit_license_the_metadata_names():
    text = (REPO / "LICENSE").read_text()
    assert text.startswith("MIT License") and "WITHOUT WARRANTY OF ANY KIND" in text
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert any(c.startswith("Programming Language :: Python :: 3.") for c in project["classifiers"])
    assert not any(c.startswith("License ::") for c in project["classifiers"])  # the SPDX expression says it


@pytest.mark.slow
def test_building_the_package_warns_of_nothing_and_carries_the_license(tmp_path):
    p = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-v", "-w", str(tmp_path), str(REPO)],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    log = p.stdout + p.stderr
    warnings = [ln for ln in log.splitlines() if re.search(r"warning", ln, re.I) and "byte-compiling" not in ln]
    assert not warnings, warnings
    (wheel,) = tmp_path.glob("magcal_mpu9150-*.whl")
    with zipfile.ZipFile(wheel) as z:
        meta = z.read(next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))).decode()
        assert any(n.endswith(".dist-info/licenses/LICENSE") for n in z.namelist())
    assert "License-Expression: MIT" in meta and "License-File: LICENSE" in meta
    assert "Classifier: Topic :: System :: Hardware" in meta


def test_the_service_unit_points_at_documentation_the_install_steps_put_there():
    unit = (REPO / "config" / "magcal@.service").read_text()
    (line,) = [ln for ln in unit.splitlines() if ln.startswith("Documentation=")]
    docs = line.split("=", 1)[1].split()
    steps = (REPO / "config" / "README.md").read_text()
    installed = dict((dst, src) for src, dst in re.findall(r"install -D -m 0644 (\S+) (/usr/share/doc/\S+)", steps))
    for uri in docs:
        assert uri.startswith("file://"), uri
        path = uri[len("file://"):]
        assert path in installed, f"{path} is not installed by config/README.md"
        assert (REPO / installed[path]).is_file()


def _run_daemon(tmp_path, journal: bool) -> str:
    log = tmp_path / ("journal.log" if journal else "plain.log")
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAGCAL_")}
    env["PYTHONPATH"] = str(REPO)
    with open(log, "w") as err:
        if journal:  # what systemd sets when stderr is the journal: that stream's device and inode
            st = os.fstat(err.fileno())
            env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
        p = subprocess.run([sys.executable, "-m", "magcal", "run", "--port", "sim://?pace=0", "--count", "200",
                            "--state-dir", str(tmp_path / ("j" if journal else "p"))],
                           stderr=err, stdout=subprocess.DEVNULL, env=env, timeout=120)
    assert p.returncode == 0
    return log.read_text()


@pytest.mark.slow
def test_log_lines_leave_the_time_to_the_journal(tmp_path):
    stamp = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d")
    journal = _run_daemon(tmp_path, journal=True).splitlines()
    assert journal and all(re.match(r"<[0-7]>magcal\.", ln) for ln in journal), journal[:3]
    assert not any(stamp.search(ln) for ln in journal)
    assert any(ln.startswith("<6>magcal.daemon: daemon started") for ln in journal)
    plain = _run_daemon(tmp_path, journal=False).splitlines()
    assert plain and all(stamp.match(ln) for ln in plain)  # in a file or at a terminal: with the time
