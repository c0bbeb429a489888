"""The page of `mapf-fleet view`: a small HTTP server (the standard library's, in threads) on
127.0.0.1 only, serving

    /             the page (static/index.html, package data: a canvas and plain JavaScript)
    /events       Server-Sent Events: "map" when the map changes, "state" at most `max_rate`
                  times a second while the fleet changes (the latest picture; nothing queues)
    /state.json   the current picture (FleetPicture.snapshot), for scripts and tests
    /map.json     the current map

Server-Sent Events rather than a WebSocket: the browser's EventSource reconnects by itself and
the server side is a plain streamed HTTP response, so no extra library is needed for it.

Loopback only: the socket is bound to 127.0.0.1 and there is no option to bind anything else;
requests whose Host header is not this loopback address are refused (403), so a web page from
elsewhere cannot reach the view through DNS rebinding.
"""

from __future__ import annotations

import html
import json
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources

from mapf_fleet.view.picture import FleetPicture

HOST = "127.0.0.1"
KEEPALIVE_S = 10.0  # an SSE comment this often, so a dead connection is noticed


def page_html() -> bytes:
    """The page, from the package data of mapf_fleet.view (installed by setup.py)."""
    return resources.files("mapf_fleet.view").joinpath("static/index.html").read_bytes()


class ViewServer:
    """Serves `picture` on http://127.0.0.1:`port`/ (port 0: a free one; see `.port`)."""

    def __init__(self, picture: FleetPicture, port: int = 0, max_rate: float = 20.0,
                 title: str = "mapf-fleet view"):
        if not max_rate > 0:
            raise ValueError(f"max_rate must be > 0, got {max_rate!r}")
        self.picture = picture
        self.min_interval = 1.0 / max_rate
        self.page = page_html().replace(b"{{TITLE}}", html.escape(title).encode("utf-8", "replace"))
        self.stopping = threading.Event()
        self.httpd = ThreadingHTTPServer((HOST, int(port)), self._handler_class())
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="view-http",
                                        daemon=True)

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    def start(self) -> "ViewServer":
        self._thread.start()
        return self

    def stop(self) -> None:
        self.stopping.set()
        with self.picture._cond:  # wake the event streams so they end
            self.picture._cond.notify_all()
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(5.0)

    def _handler_class(self):
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):  # no access log on the terminal
                pass

            def handle(self):
                try:
                    super().handle()
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the browser gave up on a request (a favicon, a closed tab)

            def _host_ok(self) -> bool:
                host = (self.headers.get("Host") or "").strip().lower()
                return host in {f"{HOST}:{server.port}", f"localhost:{server.port}"}

            def _send(self, status, body: bytes, content_type: str):
                self.send_response(status)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self):
                if not self._host_ok():
                    self._send(HTTPStatus.FORBIDDEN, b"mapf-fleet view: loopback only\n",
                               "text/plain")
                    return
                path = self.path.split("?", 1)[0]
                if path in ("/", "/index.html"):
                    self._send(HTTPStatus.OK, server.page, "text/html; charset=utf-8")
                elif path == "/state.json":
                    self._send(HTTPStatus.OK, json.dumps(server.picture.snapshot()).encode(),
                               "application/json")
                elif path == "/map.json":
                    self._send(HTTPStatus.OK, json.dumps(server.picture.map_snapshot()).encode(),
                               "application/json")
                elif path == "/events":
                    self._events()
                elif path == "/favicon.ico":  # browsers ask for it: no icon, no error
                    self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon")
                else:
                    self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")

            def _event(self, name: str, data: dict):
                self.wfile.write(f"event: {name}\ndata: {json.dumps(data)}\n\n".encode())
                self.wfile.flush()

            def _events(self):
                self.send_response(HTTPStatus.OK)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.send_header("Connection", "close")
                self.end_headers()
                self.close_connection = True
                picture = server.picture
                sent_map = sent = -1
                try:
                    while not server.stopping.is_set():
                        if picture.map_version != sent_map:
                            sent_map = picture.map_version
                            self._event("map", picture.map_snapshot())
                        if picture.version != sent:
                            snapshot = picture.snapshot()
                            sent = snapshot["version"]
                            self._event("state", snapshot)
                            # at most max_rate states a second: the next one is the latest
                            if server.stopping.wait(server.min_interval):
                                break
                        elif picture.wait_change(sent, KEEPALIVE_S) == sent:
                            self.wfile.write(b": keep-alive\n\n")
                            self.wfile.flush()
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the browser went away

        return Handler
