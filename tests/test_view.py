"""The live view (``calibrate --view``, ``run --view``): the server, and the page in a real
headless Chromium during a ``sim://`` calibration (tests/browser_support.py)."""

import http.client
import json
import re
import sys
import time

import pytest

from browser_support import chromium, require_browser, start_view, state, wait_for
from magcal.cli.view import ViewServer, page_html


def _get(server: ViewServer, path: str, host: str | None = None) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    conn.request("GET", path, headers={"Host": host or f"127.0.0.1:{server.port}"})
    r = conn.getresponse()
    body = r.read()
    conn.close()
    return r.status, body


@pytest.fixture
def server():
    s = ViewServer()
    yield s
    s.close(grace_s=0)


def test_only_the_token_and_this_machine_get_the_page(server):
    assert server.url.startswith(f"http://127.0.0.1:{server.port}/") and len(server.token) >= 20
    assert server._httpd.server_address[0] == "127.0.0.1"  # not reachable from the network
    assert _get(server, f"/{server.token}/")[0] == 200
    assert _get(server, "/")[0] == 403
    assert _get(server, "/state")[0] == 403
    wrong = server.token[:-1] + ("y" if server.token.endswith("x") else "x")  # one character off, never the token
    assert _get(server, f"/{wrong}/state")[0] == 403
    # a page elsewhere that rebinds its own name to 127.0.0.1 names its host, not this one
    assert _get(server, f"/{server.token}/state", host="evil.example:80")[0] == 403


def test_the_latest_state_is_served_and_the_server_closes_with_the_command():
    s = ViewServer()
    s.publish({"samples": 3})
    assert json.loads(_get(s, f"/{s.token}/state")[1]) == {"samples": 3}
    s.close(grace_s=0)
    with pytest.raises(OSError):
        _get(s, f"/{s.token}/state")


def test_the_page_fetches_nothing_from_elsewhere():
    html = page_html().decode()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", html)
    assert not re.search(r"""(fetch|EventSource|import)\s*\(\s*["'](https?:)?//""", html)
    assert "EventSource(\"events\")" in html  # the stream is this server's, relative to the token path


def test_under_json_the_url_goes_to_stderr_and_stdout_stays_one_document(tmp_path, capsys, monkeypatch):
    from magcal.cli import main

    monkeypatch.setenv("DISPLAY", ":0")  # even with a display, --json opens no browser
    opened = []
    monkeypatch.setattr("webbrowser.open", lambda *a, **k: opened.append(a))
    code = main(["calibrate", "--port", f"sim://?pace=0&seed=2&eeprom={tmp_path}/e.bin", "--json", "--view"])
    out = capsys.readouterr()
    assert code == 0 and json.loads(out.out)["verified"] is True
    assert re.search(r"live view: http://127\.0\.0\.1:\d+/\S{20,}/", out.err) and not opened


def test_no_browser_is_opened_without_a_display():
    from magcal.cli.view import a_browser_is_there

    if sys.platform.startswith("linux"):
        assert not a_browser_is_there({"PATH": "/usr/bin"})


@pytest.mark.slow
def test_chromium_watches_a_sim_calibration_fill_in_and_verify(tmp_path):
    """Points arrive, gaps shrink, a reload picks the stream up again, and the write is shown
    VERIFIED; the server is gone when the command ends."""
    require_browser()
    driver = chromium(tmp_path / "profile")
    proc = None
    try:
        proc, url = start_view(["calibrate", "--port", f"sim://?pace=20&seed=4&eeprom={tmp_path}/e.bin"])
        driver.get(url)
        early = wait_for(driver, lambda s: s["points"] > 0)[-1]
        driver.refresh()  # a reload gets the latest state at once and goes on
        mid = wait_for(driver, lambda s: s["updates"] >= 3 and s["points"] > early["points"])[-1]
        assert mid["gaps"] < early["gaps"]
        seen = wait_for(driver, lambda s: s["write"] == "verified" and s["ended"], timeout_s=60)
        end = seen[-1]
        assert end["badge"] == "VERIFIED" and end["gaps"] <= mid["gaps"] and end["points"] >= mid["points"]
        assert proc.wait(timeout=30) == 0
        assert "VERIFIED" in proc.stdout.read()
        assert state(driver)["badge"] == "VERIFIED"  # the page keeps the last state after the command
    finally:
        driver.quit()
        if proc is not None and proc.poll() is None:
            proc.kill()


@pytest.mark.slow
def test_run_view_shows_the_daemons_collecting_and_the_write_it_verified(tmp_path):
    """``run --view``: the page's state follows the daemon's session, then shows the calibration
    it wrote and verified; the server closes when the daemon stops."""
    proc, url = start_view(["run", "--port", f"sim://?pace=25&seed=3&eeprom={tmp_path}/e.bin", "--recalibrate",
                            "--state-dir", str(tmp_path / "state"), "--count", "2600"])
    try:
        port = int(re.search(r":(\d+)/", url).group(1))
        path = url.split(str(port), 1)[1] + "state"
        seen = []
        while proc.poll() is None:
            try:
                conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
                conn.request("GET", path)
                seen.append(json.loads(conn.getresponse().read()))
                conn.close()
            except OSError:
                break  # the daemon stopped and its server with it
            time.sleep(0.1)
        assert proc.wait(timeout=30) == 0
        states = [s for s in seen if s]
        assert any(s["status"] == "collecting" and s["points"] for s in states)
        held = [s["held"] for s in states if s["held"]]
        assert held and held[-1]["verified"] and 40 < held[-1]["field_ut"] < 60
        with pytest.raises(OSError):
            http.client.HTTPConnection("127.0.0.1", port, timeout=2).request("GET", path)
    finally:
        if proc.poll() is None:
            proc.kill()
