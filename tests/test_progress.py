"""Progress as a user sees it: in a real terminal (a pty) the long commands show what they do,
how fast and how long is left — and during ``calibrate`` a map of the directions seen and
missing with the next move; in a pipe, or with --quiet, only the results."""

import io
import itertools
import os
import pty
import re
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

from magcal.cli import main

REPO = Path(__file__).resolve().parents[1]
ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def in_terminal(*argv, timeout=600, cwd=None, columns: int = 120, lines: int = 40) -> tuple[int, str]:
    """Run ``magcal ARGV`` with stdin, stdout and stderr on a pseudo-terminal of ``columns`` ×
    ``lines``: (status, all it wrote)."""
    leader, follower = pty.openpty()
    env = dict(os.environ, PYTHONPATH=str(REPO), TERM="xterm", COLUMNS=str(columns), LINES=str(lines))
    p = subprocess.Popen([sys.executable, "-m", "magcal", *argv], stdin=follower, stdout=follower,
                         stderr=follower, env=env, close_fds=True, cwd=cwd)
    os.close(follower)
    out = bytearray()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([leader], [], [], 0.2)
        if ready:
            try:
                chunk = os.read(leader, 65536)
            except OSError:  # the terminal closed: the command has ended
                break
            if not chunk:
                break
            out += chunk
        elif p.poll() is not None:
            break
    p.wait(timeout=10)
    os.close(leader)
    return p.returncode, out.decode("utf-8", "replace")


def in_pipe(*argv, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magcal", *argv], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=timeout, stdin=subprocess.DEVNULL)


@pytest.mark.slow
def test_calibrate_in_a_terminal_maps_the_directions_and_says_where_to_turn(tmp_path):
    # a board without an accelerometer is told where to turn relative to the field; at 10× real
    # time its ~38 s of turning take ~4 s, still ~15 of the display's quarter-second frames
    code, out = in_terminal("calibrate", "--port", f"sim://?pace=10&accel=off&eeprom={tmp_path}/e.bin")
    assert code == 0, out[-2000:]
    plain = ANSI.sub("", out)
    assert "+Z │" in plain and "−Z │" in plain and "−X" in plain and "+Y" in plain  # the map and its axes
    assert re.search(r"next: aim the board's [+−][XYZ]", plain)  # which way to turn
    assert "◆◆" in plain and "██" in plain and "··" in plain  # where it points, full and empty cells
    assert re.search(r"\d+ samples \(\d+/s\)", plain) and "gives up in" in plain  # rate and time left
    assert "\x1b[" in out and out.count("next: aim") > 3  # redrawn in place as the board turns
    assert "VERIFIED" in plain


@pytest.mark.slow
def test_calibrate_quiet_or_piped_shows_no_map(tmp_path):
    # at 20 Hz the same turning is ~800 samples instead of ~1 900: the display's absence does
    # not depend on how many samples the calibration took
    code, out = in_terminal("calibrate", "--quiet", "--rate", "20", "--port", f"sim://?pace=0&eeprom={tmp_path}/e.bin")
    assert code == 0 and "│" not in out and "next: aim" not in out and "VERIFIED" in out
    p = in_pipe("calibrate", "--rate", "20", "--port", f"sim://?pace=0&eeprom={tmp_path}/f.bin")
    assert p.returncode == 0 and "│" not in p.stderr and "\x1b[" not in p.stderr + p.stdout


@pytest.mark.slow
def test_record_shows_rate_and_time_left_in_a_terminal_only(tmp_path):
    # a short output name: the line is clipped to the terminal's 120 columns, and a long
    # temporary path (as under pytest -n) pushed "left" past the edge
    # (the rate is drawn after the first half second, so 1.5 s leaves ten frames that show it;
    # the display, drawn from the first batch on, would show in a pipe within the 1 s there)
    code, out = in_terminal("record", "--port", "sim://", "--seconds", "1.5", "-o", "a.cap", cwd=tmp_path)
    plain = ANSI.sub("", out)
    assert code == 0 and re.search(r"\d+ samples/s", plain) and "left" in plain and "recorded" in plain
    p = in_pipe("record", "--port", "sim://", "--seconds", "1", "-o", str(tmp_path / "b.cap"))
    assert p.returncode == 0 and p.stderr == "" and "recorded" in p.stdout


@pytest.fixture(scope="module")
def short(tmp_path_factory):
    path = tmp_path_factory.mktemp("short") / "short.csv"
    assert main(["simulate", "-o", str(path), "--seconds", "100", "--temp-swing", "10", "--quiet"]) == 0
    return path  # 5 000 samples: a fit of a fraction of a second, a diagnosis of about a second


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def in_slow_terminal(monkeypatch):
    """``magcal ARGV`` in-process with stderr on a stand-in terminal and the display on a slow clock: long
    work is played by short work. The display's clock moves half a second each time it is read,
    so it draws after its first second, and the steps' pace gives an ETA; the real display thread
    draws, and each step waits (at most 2 s) until it is on the screen, so a fast machine misses
    no frame."""
    from magcal.cli import common

    ticks = itertools.count()

    class SlowClock(common.Progress):
        def __init__(self, quiet=False, stream=None, clock=None, every_s=0.1):
            super().__init__(quiet, stream, lambda: 0.5 * next(ticks), every_s)

    screen = _Terminal()

    def drawn(step):
        def step_and_see_it_drawn(ticker, *args):
            step(ticker, *args)
            until = time.monotonic() + 2.0
            while args[-1] not in screen.getvalue() and time.monotonic() < until:
                time.sleep(0.02)
        return step_and_see_it_drawn

    def run(*argv) -> tuple[int, str]:
        """(status, what it drew without the colour and cursor codes)."""
        with monkeypatch.context() as m:  # stderr set here: pytest's capture resets it for the test
            m.setattr(sys, "stderr", screen)
            code = main(list(argv))
        return code, ANSI.sub("", screen.getvalue())

    monkeypatch.setattr(common, "Progress", SlowClock)
    monkeypatch.setattr(common._Ticker, "share", drawn(common._Ticker.share))
    monkeypatch.setattr(common._Ticker, "doing", drawn(common._Ticker.doing))
    monkeypatch.setenv("COLUMNS", "400")  # each frame on one line, whatever the temporary path
    return run


@pytest.mark.slow
def test_a_long_fit_says_what_it_is_doing(short, in_slow_terminal, capsys):
    """What a fit is doing, drawn while it works (a long fit played by a short one on the slow
    clock); in a pipe, nothing on stderr."""
    code, plain = in_slow_terminal("fit", str(short), "--model", "ellipsoid")
    assert code == 0 and re.search(r"fit  \d+ s  fitting 5 000 samples", plain), plain[-500:]
    assert "offset_ut" in capsys.readouterr().out
    p = in_pipe("fit", str(short), "--model", "ellipsoid")
    assert p.returncode == 0 and p.stderr == ""


@pytest.mark.slow
def test_a_long_diagnosis_gives_its_step_and_an_eta(short, in_slow_terminal, capsys):
    """The step a diagnosis is in, how much of it is done and its ETA (a long diagnosis played by
    a short one on the slow clock); in a pipe with --quiet, nothing on stderr."""
    code, plain = in_slow_terminal("diagnose", str(short))
    assert code == 0 and re.search(r"5 000 samples: \w+ \(\d+ % done\)  ETA \d+ s", plain), plain[-600:]
    assert "findings" in capsys.readouterr().out
    p = in_pipe("diagnose", str(short), "--quiet")
    assert p.returncode == 0 and p.stderr == ""


def test_at_a_terminal_with_no_device_named_it_asks_which(tmp_path):
    """No --port, no MAGCAL_PORT, no config: a terminal user is asked (and may name the simulator)."""
    leader, follower = pty.openpty()
    env = {k: v for k, v in os.environ.items() if not k.startswith("MAGCAL_")}
    env.update(PYTHONPATH=str(REPO), TERM="xterm", HOME=str(tmp_path))
    p = subprocess.Popen([sys.executable, "-m", "magcal", "show"], stdin=follower, stdout=follower,
                         stderr=follower, env=env, close_fds=True, cwd=tmp_path)
    os.close(follower)
    seen = b""
    deadline = time.monotonic() + 60
    while b"port to use" not in seen and time.monotonic() < deadline:
        if select.select([leader], [], [], 0.2)[0]:
            seen += os.read(leader, 4096)
    os.write(leader, b"sim://?pace=0\n")
    while p.poll() is None and time.monotonic() < deadline:
        if select.select([leader], [], [], 0.2)[0]:
            try:
                seen += os.read(leader, 4096)
            except OSError:
                break
    p.wait(timeout=10)
    os.close(leader)
    text = seen.decode("utf-8", "replace")
    assert "port to use" in text and "sim:// for the simulator" in text
    assert p.returncode == 1 and "none stored" in text  # it went on with the answer
