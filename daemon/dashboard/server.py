"""The dashboard's HTTP side: the page from `static/`, a snapshot, live updates, the reset relay.

Standard library only (`http.server.ThreadingHTTPServer`): one thread per
connection is plenty for the few screens of a shop floor (`book.MAX_CLIENTS`).
Clients cannot hold threads at will: a request must arrive whole within
`REQUEST_TIMEOUT_S` (so must the next one on a kept-alive connection), a write
blocked `SEND_TIMEOUT_S` ends the connection, and past `MAX_CONNECTIONS` in all,
or `MAX_CONNECTIONS_PER_PEER` from one address, a new connection is closed at
once, without a thread (systemd's TasksMax=128 must leave room for Zenoh's
threads; one misbehaving client must leave room for the other screens). A peer
hanging up is ordinary: no traceback.

- `GET /` and `/static/<file>`: the page, its script and style, from the package;
- `GET /events`: Server-Sent Events; the first event is the whole snapshot, then
  batches of updates (one event holds every update waiting, so 20 machines at
  10 revolutions a second cost a few writes a second, not 200);
- `POST /api/reset/<machine>`: one step of the reset exchange, relayed
  (zenoh_side.py). It needs the header `X-Millsense: reset`, which a form on
  another site cannot send without a CORS preflight this server never grants.

Every answer first reads what is left of its request's body (`_drain_body`):
a refused request's body (403, 404, 405, 413, 421, ...) left unread would be
taken for the next request on the kept-alive connection (issue 36, finding 7:
`501 Unsupported method ('{"step":…}GET')`, and the page's next reset broken).
A body over `DRAIN_MAX_BYTES`, a length that is not a number, or a chunked one
is not read: the answer says `Connection: close` and the connection ends.

The reset is offered (`reset_offered` in `/api/info`) only where a browser gives
the page WebCrypto: over HTTPS, or on a loopback address.
"""

from __future__ import annotations

import io
import ipaddress
import json
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any

import structlog

from millsense.daemon.dashboard.book import Book, TooManyPages
from millsense.daemon.dashboard.zenoh_side import RelayRefused
from millsense.daemon.logging_setup import RateLimitedLogger

STATIC = {"app.js": "text/javascript; charset=utf-8", "app.css": "text/css; charset=utf-8",
          "index.html": "text/html; charset=utf-8"}
MAX_BODY_BYTES = 4096
# The most of an unread body read (and thrown away) to keep a connection: more, and it is closed instead.
DRAIN_MAX_BYTES = 64 * 1024
KEEPALIVE_S = 10.0
REQUEST_TIMEOUT_S = 5.0  # request line, headers and body, in all; also the wait for the next request
SEND_TIMEOUT_S = 30.0  # one write blocked this long: the page stopped reading
MAX_CONNECTIONS = 64  # every page (32) and as many requests; TasksMax=128 leaves the rest to Zenoh
# A peer's pages (book.MAX_CLIENTS_PER_PEER = 8) and as many requests: a client that opens connections
# and never finishes a request (each held REQUEST_TIMEOUT_S) fills its own share, not the server.
MAX_CONNECTIONS_PER_PEER = 16
# Updates are held this long at most before they go out, so one write carries many.
BATCH_S = 0.05
SECURITY_HEADERS = {
    # Nothing from elsewhere: no CDN, no inline script, no framing by another site.
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _static(name: str) -> bytes:
    return resources.files("millsense.daemon.dashboard").joinpath("static", name).read_bytes()


class DashboardServer(ThreadingHTTPServer):
    daemon_threads = True  # an open event stream must not keep the process alive at shutdown
    request_timeout_s = REQUEST_TIMEOUT_S
    max_connections = MAX_CONNECTIONS
    max_connections_per_peer = MAX_CONNECTIONS_PER_PEER

    def __init__(self, address: tuple[str, int], book: Book, relay: Any, https: bool):
        self.book, self.relay, self.https = book, relay, https
        self.connections = self.refused_connections = 0
        self.peer_connections: dict[str, int] = {}  # open connections by peer address; a peer at 0 is removed
        self._count_lock = threading.Lock()
        # A flood of refusals or failures is one line per 10 s, with a count.
        self.log = RateLimitedLogger(structlog.get_logger("millsense.dashboard"))
        self.loopback = is_loopback(address[0])
        self.reset_offered = https or self.loopback
        self.stopping = threading.Event()
        self.files = {name: _static(name) for name in STATIC}
        if ":" in address[0]:
            import socket

            self.address_family = socket.AF_INET6
        super().__init__(address, Handler)

    def process_request(self, request: Any, client_address: Any) -> None:
        peer = client_address[0]
        with self._count_lock:
            from_peer = self.peer_connections.get(peer, 0)
            if from_peer >= self.max_connections_per_peer:
                full = f"{from_peer} connections open from {peer} ({self.max_connections_per_peer} per address)"
            elif self.connections >= self.max_connections:
                full = f"{self.max_connections} connections open"
            else:
                full = ""
                self.connections += 1
                self.peer_connections[peer] = from_peer + 1
        if full:
            self._refuse(request, client_address, full)
            return
        try:
            super().process_request(request, client_address)
        except RuntimeError as exc:  # "can't start new thread": TasksMax reached all the same
            self._ended(peer)
            self._refuse(request, client_address, str(exc))

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._ended(client_address[0])

    def _ended(self, peer: str) -> None:
        with self._count_lock:
            self.connections -= 1
            left = self.peer_connections.pop(peer) - 1
            if left:
                self.peer_connections[peer] = left

    def _refuse(self, request: Any, client_address: Any, reason: str) -> None:
        """Close a connection unanswered (no thread to answer it), counted; said before the close."""
        with self._count_lock:
            self.refused_connections += 1
        self.log.warning("dashboard_connection_refused", key="refused", peer=client_address[0], reason=reason,
                         refused=self.refused_connections)
        self.shutdown_request(request)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """One line, not socketserver's traceback: the handler failed in a way it did not expect."""
        exc = sys.exc_info()[1]
        self.log.warning("dashboard_request_failed", key="failed", peer=client_address[0],
                         error=f"{type(exc).__name__}: {exc}")


class _DeadlineReader(io.RawIOBase):
    """The connection's reads, each allowed only what is left of the request's time.

    A socket timeout alone bounds one read: a client sending a byte every few
    seconds would hold its thread for ever."""

    def __init__(self, handler: Handler):
        self.handler = handler

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        sock = self.handler.connection
        left_s = self.handler.read_by - time.monotonic()
        if left_s <= 0:
            raise TimeoutError("the request did not arrive in time")
        sock.settimeout(left_s)
        try:
            return sock.recv_into(buffer)
        finally:
            sock.settimeout(self.handler.timeout)  # writes (an event stream) have their own bound


class Handler(BaseHTTPRequestHandler):
    server: DashboardServer
    protocol_version = "HTTP/1.1"
    timeout = SEND_TIMEOUT_S  # set on the socket by socketserver; reads have the shorter deadline above
    read_by = 0.0  # time.monotonic() by which the current request must have been read
    body_done = True  # the current request's body has been read (or there is none to read)

    def setup(self) -> None:
        super().setup()
        self.rfile.close()
        self.rfile = io.BufferedReader(_DeadlineReader(self))

    def handle(self) -> None:
        try:
            super().handle()
        except OSError:
            # The peer hung up, reset, stalled past a deadline or spoke no TLS: ordinary, not worth a line.
            self.close_connection = True

    def handle_one_request(self) -> None:
        self.read_by = time.monotonic() + self.server.request_timeout_s
        self.body_done = False
        super().handle_one_request()

    def _drain_body(self) -> None:
        """Read and drop the request's body, so the connection's next request starts where it should.

        Up to DRAIN_MAX_BYTES, within the request's deadline; a larger, chunked or unreadable one
        is not read and the connection is closed after the answer (`Connection: close`)."""
        self.body_done = True
        if self.headers is None:
            return
        if self.headers.get("Transfer-Encoding"):
            self.close_connection = True  # chunked: not worth decoding only to throw away
            return
        text = self.headers.get("Content-Length")
        if text is None:
            return
        try:
            left = int(text)
        except ValueError:
            left = -1
        if not 0 <= left <= DRAIN_MAX_BYTES:
            self.close_connection = True
            return
        while left > 0:
            chunk = self.rfile.read(min(left, 16384))
            if not chunk:
                self.close_connection = True  # the peer stopped sending: nothing more can follow
                return
            left -= len(chunk)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - http.server's name
        pass  # a request per page load is not worth a log line; the command's own events say what matters

    def _send(self, status: int, body: bytes, content_type: str, headers: dict[str, str] | None = None) -> None:
        if not self.body_done:
            self._drain_body()
        self.send_response(status)
        if self.close_connection:
            self.send_header("Connection", "close")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        for k, v in SECURITY_HEADERS.items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, value: Any, headers: dict[str, str] | None = None) -> None:
        self._send(status, json.dumps(value, allow_nan=False, default=str).encode(), "application/json", headers)

    def _host_refused(self) -> bool:
        """On a loopback address, only a loopback Host: a web site whose name an attacker re-points at
        127.0.0.1 (DNS rebinding) would otherwise read the page's data as its own origin."""
        if not self.server.loopback:
            return False
        host = (self.headers.get("Host") or "").strip()
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        if is_loopback(name.strip("[]")):
            return False
        self._json(421, {"ok": False, "error": "a dashboard on a loopback address answers only to localhost"})
        return True

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        if self._host_refused():
            return
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(200, self.server.files["index.html"], STATIC["index.html"])
        elif path.startswith("/static/") and path[len("/static/"):] in STATIC:
            name = path[len("/static/"):]
            self._send(200, self.server.files[name], STATIC[name])
        elif path == "/api/info":
            self._json(200, {"reset_offered": self.server.reset_offered, "https": self.server.https})
        elif path == "/api/snapshot":
            self._json(200, self.server.book.snapshot())
        elif path == "/events":
            self._events()
        else:
            self._json(404, {"ok": False, "error": "not found"})

    def do_POST(self) -> None:  # noqa: N802
        if self._host_refused():
            return
        path = self.path.split("?", 1)[0]
        prefix = "/api/reset/"
        if not path.startswith(prefix):
            self._json(404, {"ok": False, "error": "not found"})
            return
        if not self.server.reset_offered:
            self._json(403, {"ok": False, "error": "the reset is offered only over HTTPS (--cert, --key) or on "
                                                   "localhost"})
            return
        if self.headers.get("X-Millsense") != "reset":
            self._json(403, {"ok": False, "error": "missing header X-Millsense: reset"})
            return
        if self.headers.get("Content-Length") is None or self.headers.get("Transfer-Encoding"):
            # Chunked (with or without a length beside it, which it would override): refused, the connection closed.
            self._json(411, {"ok": False, "error": "a body with Content-Length (not chunked) is required"})
            return
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if not 0 < length <= MAX_BODY_BYTES:
            # The body is drained (up to DRAIN_MAX_BYTES) or the connection closed by the answer.
            self._json(413, {"ok": False, "error": f"a body of 1 to {MAX_BODY_BYTES} bytes is required"})
            return
        try:
            body = self.rfile.read(length)
            self.body_done = True
            request = json.loads(body)
            replies = self.server.relay.relay_reset(path[len(prefix):], request)
        except (UnicodeDecodeError, ValueError) as exc:  # RelayRefused is a ValueError too
            reason = str(exc) if isinstance(exc, RelayRefused) else "the body is not JSON"
            self._json(400, {"ok": False, "error": reason})
            return
        except Exception as exc:  # noqa: BLE001 - Zenoh closing or refusing: an answer, not a traceback
            self._json(502, {"ok": False, "error": f"relay failed: {type(exc).__name__}"})
            return
        self._json(200, {"ok": True, "replies": replies})

    def _not_allowed(self) -> None:
        """Any other method: 405 in JSON, the body drained like every refusal's (http.server's 501 is HTML
        and always closes)."""
        if self._host_refused():
            return
        self._json(405, {"ok": False, "error": f"method {self.command} not allowed"}, {"Allow": "GET, POST"})

    do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _not_allowed  # noqa: N815 - http.server's names

    def _events(self) -> None:
        book = self.server.book
        try:
            client = book.subscribe(self.client_address[0])
        except TooManyPages as exc:
            self._json(503, {"ok": False, "error": str(exc)})
            return
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            self.close_connection = True
            self._event({"kind": "snapshot", **book.snapshot()})
            while not self.server.stopping.is_set():
                updates = client.take(KEEPALIVE_S)
                if client.closed:
                    break
                if not updates:
                    self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
                    continue
                self.server.stopping.wait(BATCH_S)
                updates += client.take(0)
                self._event({"kind": "batch", "updates": updates, "dropped": client.dropped})
        except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError):
            pass  # the page went away
        finally:
            book.unsubscribe(client)

    def _event(self, value: dict) -> None:
        data = json.dumps(value, allow_nan=False, default=str, separators=(",", ":"))
        self.wfile.write(f"data: {data}\n\n".encode())
        self.wfile.flush()
