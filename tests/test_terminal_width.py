"""The live display fits the terminal it is drawn on: at 80 columns every line of a whole
``calibrate`` session is at most 80 characters wide and its numbers are whole (wrapped between
words, never cut); the map's every glyph is in the legend; the width is read from stderr, the
stream the display is drawn on, not from stdout."""

import os
import pty
import re
import select
import subprocess
import sys
from pathlib import Path

import pytest

from magcal.cli.common import stream_columns, wrap_visible
from magcal.cli.coverage_map import EMPTY, FULL, HERE, LEGEND, NEXT, SHADES

REPO = Path(__file__).resolve().parents[1]
ESC = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def _in_terminal(argv, columns: int, timeout_s: float = 120) -> tuple[int, str]:
    from test_progress import in_terminal

    return in_terminal(*argv, timeout=timeout_s, columns=columns, lines=24)


def _screen_lines(out: str) -> list[str]:
    """Every line as drawn: split where the display moves the cursor or starts a line."""
    return [part for part in re.split(r"\r|\n|\x1b\[\d*[AJK]", out) if part.strip()]


@pytest.mark.slow
def test_a_whole_calibrate_session_fits_80_columns_with_every_number_whole(tmp_path):
    # 10× real time: the whole session (~38 s of turning) in ~4 s, still ~15 frames to measure
    code, out = _in_terminal(["calibrate", "--port", "sim://?pace=10&seed=2"], 80)
    assert code == 0, out[-2000:]
    lines = [ESC.sub("", x) for x in _screen_lines(out)]
    too_wide = [x for x in lines if len(x) > 80]
    assert not too_wide, too_wide[:3]
    text = "\n".join(lines)
    # the status line's numbers, the countdown and the gates waited on are there whole
    assert re.search(r"\d+ samples \(\d+/s\), \d+% of directions\s+\(need \d+%\), \d+ kept,\s+gives\s+up\s+in\s+(\d+ s|\d+:\d\d)\n",
                     text + "\n"), text[-3000:]
    assert re.search(r"waiting on: (min_\w+|solvable|\w+)(, \w+)*\n", text + "\n")
    assert re.search(r"offset \[-?\d+\.\d -?\d+\.\d -?\d+\.\d\] µT, \|B\| \d+\.\d µT", text)
    assert LEGEND in text


def test_every_glyph_the_map_draws_is_in_the_legend():
    for glyph in (FULL, EMPTY, HERE, NEXT, *SHADES):
        assert glyph in LEGEND, glyph


def test_a_long_line_wraps_between_words_and_keeps_its_numbers():
    line = "collecting: 1234 samples (50/s), 45% of directions (need 55%), 201 kept, 2:30 left  offset [12.3 -4.5 6.7]"
    parts = wrap_visible(line, 40)
    assert all(len(p) <= 40 for p in parts) and len(parts) > 1
    assert " ".join(p.strip() for p in parts).split() == line.split()
    coloured = "\x1b[32m██\x1b[0m " * 30
    assert all(len(ESC.sub("", p)) <= 40 for p in wrap_visible(coloured, 40))


def test_the_width_comes_from_the_stream_drawn_on(monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)
    leader, follower = pty.openpty()
    try:
        import fcntl
        import struct
        import termios

        fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
        with os.fdopen(os.dup(follower), "w") as tty:
            assert stream_columns(tty) == 80
    finally:
        os.close(leader)
        os.close(follower)


@pytest.mark.slow
def test_diagnose_twin_with_json_on_stdout_draws_its_stages_at_the_terminals_width(tmp_path):
    data = REPO / "tests" / "data" / "hmc5883l_sunsided_full_sphere_every3rd.csv"
    leader, follower = pty.openpty()
    import fcntl
    import struct
    import termios

    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    env.update(PYTHONPATH=str(REPO), TERM="xterm")
    with open(tmp_path / "d.json", "w") as stdout:
        p = subprocess.run([sys.executable, "-m", "magcal", "diagnose", str(data), "--twin", "--draws", "10", "--json"],
                           stdin=follower, stdout=stdout, stderr=follower, env=env, timeout=300)
    os.close(follower)
    out = b""
    while select.select([leader], [], [], 0.1)[0]:
        try:
            chunk = os.read(leader, 65536)
        except OSError:
            break
        if not chunk:
            break
        out += chunk
    os.close(leader)
    assert p.returncode == 0
    lines = [ESC.sub("", x) for x in _screen_lines(out.decode("utf-8", "replace"))]
    assert lines and all(len(x) <= 80 for x in lines), [x for x in lines if len(x) > 80][:3]
    assert any(re.search(r"\[\d+/\d+, ETA ", x) for x in lines), lines[-10:]
