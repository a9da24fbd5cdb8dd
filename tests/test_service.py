"""The systemd unit (config/magcal@.service), checked by systemd's own tools without a running
systemd: ``systemd-analyze verify`` finds nothing to say, ``systemd-analyze security`` rates its
exposure at most 3.0, and it survives an unplug (started by its device, not bound to it), does
not loop on a configuration error and keeps its state private.

Needs ``systemd-analyze`` (Debian: ``apt-get install systemd``; ``.ci/run`` installs it). Without
it the test skips, and fails under CI (``CI=true``)."""

import os
import re
import shutil
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
UNIT = os.path.join(ROOT, "config", "magcal@.service")
MAX_EXPOSURE = 3.0


def _analyze() -> str:
    tool = shutil.which("systemd-analyze")
    if tool is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but systemd-analyze is missing (apt-get install systemd)")
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    return tool


@pytest.fixture
def instance(tmp_path):
    """The template as the instance for /dev/ttyACM0 (what `systemctl enable magcal@ttyACM0` loads)."""
    path = tmp_path / "magcal@ttyACM0.service"
    shutil.copy(UNIT, path)
    return path


def _settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    with open(UNIT, encoding="utf-8") as fh:
        for line in fh:
            m = re.match(r"^([A-Za-z]+)=(.*)$", line.strip())
            if m:
                out.setdefault(m.group(1), []).append(m.group(2))
    return out


def test_systemd_finds_nothing_wrong_with_the_unit(instance):
    tool = _analyze()
    p = subprocess.run([tool, "verify", str(instance)], capture_output=True, text=True, timeout=120)
    said = [ln for ln in (p.stdout + p.stderr).splitlines() if ln.strip()]
    assert p.returncode == 0 and said == [], said


def test_the_unit_is_hardened(instance):
    tool = _analyze()
    p = subprocess.run([tool, "security", "--offline=yes", "--no-pager", str(instance)], capture_output=True,
                       text=True, timeout=120)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", p.stdout)
    assert m, p.stdout[-2000:] + p.stderr[-2000:]
    assert float(m.group(1)) <= MAX_EXPOSURE, p.stdout


def test_the_unit_survives_replug_and_does_not_loop_on_a_config_error():
    s = _settings()
    assert "BindsTo" not in s  # an unplug would stop it, and nothing would start it again
    assert s["WantedBy"] == ["dev-%i.device"]  # the device (re)appearing starts it
    assert s["Restart"] == ["on-failure"]
    from magcal.cli.exits import Exit

    assert s["RestartPreventExitStatus"] == [str(int(Exit.USAGE))]  # config/command-line errors
    assert s["UMask"] == ["0077"] and s["StateDirectoryMode"] == ["0700"]
