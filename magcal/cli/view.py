"""The live 3-D view in the browser: ``magcal calibrate --view`` and ``magcal run --view``.

A small HTTP server on the loopback interface only (127.0.0.1, a free port the system picks),
behind a random token in the URL path: ``http://127.0.0.1:PORT/TOKEN/``. A request without
the token — or naming another host, as a page from elsewhere rebinding a name to 127.0.0.1
would — gets 403. The page (``view.html``, shipped in the package, nothing fetched from
elsewhere) receives the state by Server-Sent Events (``TOKEN/events``), one JSON document per
update, as soon as the command publishes it; ``TOKEN/state`` gives the latest once. What the
state holds is computed by ``magcal.logic.view`` (pure); this module only serves it.

The server lives as long as the command: ``close`` sends the last state (the write VERIFIED,
or why not) to every open page, ends their streams and stops listening. A reloaded page gets
the latest state at once. The URL is printed on stderr; a browser is opened only when one with
a display is there, and never under ``--json``.
"""

from __future__ import annotations

import hmac
import json
import os
import secrets
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

HOST = "127.0.0.1"
EVERY_S = 0.05  # the command publishes at most 20 states a second
PING_S = 1.0  # an idle stream gets a comment this often (a closed page is noticed)
GRACE_S = 1.5  # on close: how long the last state may take to reach the open pages


def add_view_option(p) -> None:
    p.add_argument("--view", action="store_true",
                   help="show the calibration live in the browser: the points on a 3-D sphere, the gaps, the "
                        "numbers and the next turn (a page on 127.0.0.1 with a random token; its URL is printed)")


def page_html() -> bytes:
    """The page, as shipped in the package."""
    return resources.files("magcal.cli").joinpath("view.html").read_bytes()


class ViewServer:
    """Serves the page and the latest published state to pages holding the token."""

    def __init__(self, host: str = HOST, port: int = 0):
        self.token = secrets.token_urlsafe(18)
        self._page = page_html()
        self._cond = threading.Condition()
        self._version, self._data, self._closed = 0, b"null", False
        self._streams: dict[int, int] = {}  # open stream → the version it last sent
        self._httpd = ThreadingHTTPServer((host, port), _handler_for(self))
        self._httpd.daemon_threads = True
        self.port = self._httpd.server_address[1]
        self.url = f"http://{HOST}:{self.port}/{self.token}/"
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.05},
                                        name="magcal-view", daemon=True)
        self._thread.start()

    # -- the command's side ----------------------------------------------------------------------
    def publish(self, state: dict) -> None:
        data = json.dumps(state, separators=(",", ":"), allow_nan=False).encode()
        with self._cond:
            self._version += 1
            self._data = data
            self._cond.notify_all()

    def close(self, grace_s: float = GRACE_S) -> None:
        """End every stream once it has sent the last state (at most ``grace_s``), then stop."""
        end = time.monotonic() + grace_s
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            while any(v < self._version for v in self._streams.values()) and time.monotonic() < end:
                self._cond.wait(max(0.0, end - time.monotonic()))
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout=2.0)

    # -- the pages' side -------------------------------------------------------------------------
    def allowed(self, path: str, host: str | None) -> str | None:
        """What a request asks for under the token (``""`` the page, ``events``, ``state``), or
        None when it does not hold the token or names a host other than this server."""
        if host not in (f"{HOST}:{self.port}", f"localhost:{self.port}"):
            return None
        parts = path.split("?", 1)[0].split("/")
        if len(parts) < 3 or parts[0] != "" or not hmac.compare_digest(parts[1].encode(), self.token.encode()):
            return None
        return "/".join(parts[2:])

    def latest(self) -> tuple[int, bytes]:
        with self._cond:
            return self._version, self._data

    def wait(self, stream: int, sent: int, timeout_s: float) -> tuple[int, bytes, bool]:
        """For an open stream that sent version ``sent``: the next state (or the same after
        ``timeout_s``) and whether the command has ended."""
        with self._cond:
            self._streams[stream] = sent
            self._cond.notify_all()
            if self._version <= sent and not self._closed:
                self._cond.wait(timeout_s)
            return self._version, self._data, self._closed

    def forget(self, stream: int) -> None:
        with self._cond:
            self._streams.pop(stream, None)
            self._cond.notify_all()


def _handler_for(server: ViewServer):
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *_):  # the command's own output stays readable
            pass

        def do_GET(self):  # noqa: N802 (the http.server name)
            what = server.allowed(self.path, self.headers.get("Host"))
            if what is None:
                return self._send(403, b"forbidden: this page needs the URL magcal printed\n", "text/plain")
            if what == "":
                return self._send(200, server._page, "text/html; charset=utf-8")
            if what == "state":
                return self._send(200, server.latest()[1], "application/json")
            if what == "events":
                return self._stream()
            return self._send(404, b"not found\n", "text/plain")

        def _send(self, code: int, body: bytes, kind: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Content-Security-Policy",
                             "default-src 'self'; script-src 'unsafe-inline'; style-src 'unsafe-inline'")
            self.end_headers()
            self.wfile.write(body)

        def _stream(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            self.close_connection = True
            key = id(self)
            sent = 0
            try:
                while True:
                    version, data, closed = server.wait(key, sent, PING_S)
                    if version > sent:
                        self.wfile.write(b"id: %d\ndata: %s\n\n" % (version, data))
                        sent = version
                    elif closed:
                        self.wfile.write(b"event: end\ndata: {}\n\n")
                        self.wfile.flush()
                        server.wait(key, sent, 0)
                        return
                    else:
                        self.wfile.write(b": ping\n\n")
                    self.wfile.flush()
            except (BrokenPipeError, ConnectionResetError, OSError):
                return
            finally:
                server.forget(key)

    return Handler


def a_browser_is_there(environ=None) -> bool:
    """A graphical browser can be opened: a display (or macOS/Windows) and one ``webbrowser``
    knows. A text browser in the same terminal would take over the live display."""
    import webbrowser

    environ = os.environ if environ is None else environ
    if sys.platform.startswith("linux") and not (environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY")):
        return False
    try:
        webbrowser.get()
    except webbrowser.Error:
        return False
    return True


def start(json_output: bool, stream=None) -> ViewServer:
    """Start the server, say its URL on ``stream`` (stderr) and open a browser on it when one is
    there and the output is not JSON."""
    import webbrowser

    stream = stream or sys.stderr
    server = ViewServer()
    print(f"live view: {server.url}  (this machine only; closes with the command)", file=stream, flush=True)
    if not json_output and a_browser_is_there():
        webbrowser.open(server.url, new=2)
    return server


class LiveView:
    """A calibration's states published to the view, at most every ``EVERY_S`` on the command's
    clock (the terminal's own display is untouched)."""

    every_s = EVERY_S

    def __init__(self, server: ViewServer, timeout_s: float | None, clock=time.monotonic):
        self.server = server
        self.timeout_s = timeout_s
        self.clock = clock
        self.t0: float | None = None  # the first state: collecting has begun
        self._last = -1e9
        self.published = 0

    def progress(self, session, force: bool = False, **outcome) -> None:
        from ..logic.view import page_state

        now = self.clock()
        if not force and now - self._last < self.every_s:
            return
        self._last = now
        self.t0 = now if self.t0 is None else self.t0
        state = page_state(session, elapsed_s=now - self.t0, timeout_s=self.timeout_s, **outcome)
        self.server.publish(state.to_dict())
        self.published += 1

    def finish(self, outcome) -> None:
        """The last state — the write VERIFIED, or why not — then the server closes."""
        try:
            if outcome is not None:
                self.progress(outcome.session, force=True, written=outcome.written, verified=outcome.verified)
        finally:
            self.server.close()


class DaemonView:
    """``run --view``: the daemon's collecting session and the calibration it last wrote and
    verified, published from its own loop (``on_sample``, on the daemon's thread) at most every
    ``EVERY_S``."""

    def __init__(self, server: ViewServer, clock=time.monotonic):
        self.live = LiveView(server, None, clock)
        self.daemon = None

    def on_sample(self, epoch: int, sample, force: bool = False) -> None:
        if self.daemon is None:
            return
        from ..core.calibration import Calibration

        last = self.daemon.writer.last
        held = Calibration.from_dict(last["calibration"]) if last else None
        self.live.progress(self.daemon.recalibrator.session, force=force, held=held)

    def close(self) -> None:
        try:
            self.on_sample(0, None, force=True)
        finally:
            self.live.server.close()
