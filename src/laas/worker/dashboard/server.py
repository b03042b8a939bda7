"""The live map's HTTP server (stdlib `http.server`, one thread per connection).

    GET /             the page (one self-contained HTML file: no CDN, no tiles)
    GET /api/lanes    the map's lanes, GeoJSON in WGS 84 (`lanes_geojson`)
    GET /api/state    what a new page is shown first: live pseudonyms, areas, stats
    GET /api/events   server-sent events: hello, then batch, areas and stats (`Feed`)

An events connection is served by its own handler thread from its own bounded queue.
Its socket's send buffer is kept small (`send_buffer`), so events for a slow browser
wait in that queue, where the oldest are dropped, rather than in the kernel, where they
would arrive minutes late.
"""

from __future__ import annotations

import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib.resources import files
from typing import Any

from laas.errors import ConfigError
from laas.worker.dashboard.feed import Feed, sse
from laas.worker.dashboard.views import lanes_geojson
from laas.worker.service import LaasService
from ldm import Provider

__all__ = ["DashboardServer", "page"]

_KEEPALIVE = 15.0  # s between comment lines on an idle event stream
_SOCKET_TIMEOUT = 30.0  # s a write to a client may block before it is dropped
_CSP = (
    "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
    "connect-src 'self'; img-src 'self' data:"
)  # the page may load nothing from anywhere else


def page() -> bytes:
    """The page, from the package (``laas/worker/dashboard/static/index.html``)."""
    return files("laas.worker.dashboard").joinpath("static/index.html").read_bytes()


class DashboardServer:
    """The live map of a running worker, served on a thread until `stop`.

    `port` 0 picks a free port (`url` tells which). `queue` is each client's bound in
    events, `send_buffer` its socket's send buffer in bytes.
    """

    def __init__(
        self,
        service: LaasService,
        provider: Provider | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        queue: int = 256,
        send_buffer: int = 65_536,
    ) -> None:
        self.feed = Feed(service, provider, queue=queue)
        lanes = json.dumps(lanes_geojson(service.engine.map)).encode()
        html = page()
        try:
            self._server = _Server((host, port), _Handler)
        except (OSError, OverflowError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise ConfigError(
                f"cannot serve the live map on {host}:{port}: {reason}; choose another "
                "--http port (0 picks a free one)"
            ) from None
        self._server.feed = self.feed
        self._server.page = html
        self._server.lanes = lanes
        self._server.send_buffer = send_buffer
        self.host = host
        self.port: int = self._server.server_address[1]
        self.feed.start()
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="laas-dashboard-http", daemon=True
        )
        self._thread.start()

    @property
    def url(self) -> str:
        """The page's address (an address of 0.0.0.0 shown as 127.0.0.1)."""
        host = "127.0.0.1" if self.host in ("", "0.0.0.0") else self.host
        return f"http://{host}:{self.port}/"

    def stop(self) -> None:
        """Stop serving: event streams end, the service's observer is given back."""
        self.feed.stop()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(5.0)

    def __enter__(self) -> DashboardServer:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    feed: Feed
    page: bytes
    lanes: bytes
    send_buffer: int


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = _SOCKET_TIMEOUT

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(200, "text/html; charset=utf-8", self.server.page)
        elif path == "/api/lanes":
            self._send(200, "application/geo+json", self.server.lanes)
        elif path == "/api/state":
            body = json.dumps(self.server.feed.state()).encode()
            self._send(200, "application/json", body)
        elif path == "/api/events":
            self._events()
        else:
            text = b"not found; the live map is at /, its data at /api/lanes, /api/state and "
            text += b"/api/events\n"
            self._send(404, "text/plain; charset=utf-8", text)

    def _events(self) -> None:
        feed = self.server.feed
        self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.server.send_buffer)
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Accel-Buffering", "no")
        self.end_headers()
        client = feed.subscribe()
        told = 0  # events dropped for this client that it has been told of
        try:
            while not feed.closed:
                event = client.next(_KEEPALIVE)
                self.wfile.write(event if event is not None else b": keep-alive\n\n")
                if client.dropped != told:
                    told = client.dropped
                    self.wfile.write(sse("dropped", {"dropped": told}))
                self.wfile.flush()
        except OSError:  # the page went away, or stopped reading for _SOCKET_TIMEOUT
            pass
        finally:
            feed.unsubscribe(client)
            self.close_connection = True

    def _send(self, code: int, content_type: str, body: bytes) -> None:
        self.send_response(code)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("Content-Security-Policy", _CSP)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        """No access log: a page reconnects its event stream whenever it is reloaded."""
