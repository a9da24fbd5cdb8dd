"""A real headless Chromium driven by Selenium, for the live view's test and bench.

Debian's ``chromium`` with its ``chromium-driver`` (both installed by ``.ci/run`` and ``make
toolchain``) and the ``selenium`` package (the ``test`` extra). The driver is named by its path,
so Selenium never looks for a browser or driver to download. Missing, the test skips — and
fails under CI (``CI=true``), where they are installed on purpose.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time

import pytest


def missing() -> str | None:
    """What is missing for a browser test, or None."""
    if not (shutil.which("chromium") or shutil.which("chromium-browser")):
        return "chromium is not installed (apt-get install chromium)"
    if not shutil.which("chromedriver"):
        return "chromedriver is not installed (apt-get install chromium-driver)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[test]')"
    return None


def require_browser() -> None:
    problem = missing()
    if problem:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true but {problem}")
        pytest.skip(problem)


def chromium(profile_dir, width: int = 1280, height: int = 960):
    """A headless Chromium under Selenium (the caller quits it)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium") or shutil.which("chromium-browser")
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--no-first-run", "--disable-extensions", f"--window-size={width},{height}",
                 f"--user-data-dir={profile_dir}"):
        opts.add_argument(flag)
    return webdriver.Chrome(service=Service(executable_path=shutil.which("chromedriver")), options=opts)


def start_view(argv: list[str], cwd=None) -> tuple[subprocess.Popen, str]:
    """Start ``magcal <argv> --view`` and return the process and the URL it printed."""
    proc = subprocess.Popen([sys.executable, "-m", "magcal", *argv, "--view"], cwd=cwd, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "DISPLAY": ""})
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        found = re.search(r"live view: (http://127\.0\.0\.1:\d+/\S+/)", line or "")
        if found:
            return proc, found.group(1)
        if not line and proc.poll() is not None:
            break
    proc.kill()
    raise AssertionError(f"magcal printed no live-view URL: {proc.stderr.read()}")


def state(driver) -> dict:
    """What the page holds: its update count, the last state's numbers and the badge shown."""
    return driver.execute_script(
        "const v = window.magcalView || {}; const s = v.state;"
        "return {updates: v.updates || 0, ended: !!v.ended,"
        " points: s ? s.points.length : 0, gaps: s ? s.motioncal.gaps_pct : null,"
        " write: s ? s.write : null, badge: document.getElementById('badge').textContent};")


def wait_for(driver, check, timeout_s: float = 30.0, every_s: float = 0.05) -> list[dict]:
    """Page states sampled until ``check(state)`` holds (the last one does); AssertionError on
    timeout with what was seen."""
    seen = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        seen.append(state(driver))
        if check(seen[-1]):
            return seen
        time.sleep(every_s)
    raise AssertionError(f"the page never reached the state asked for; last seen: {seen[-3:]}")
