"""The dashboard server against misbehaving clients: idle and slow requests, floods, greedy peers, hang-ups.

A real server on 127.0.0.1 with real sockets; other peers are other loopback
addresses (127.0.0.2, ...), which Linux routes to the same host. Deadlines are
shortened on the server under test (`request_timeout_s`) and every wait polls
with a generous bound, so a slow machine only makes a test slower.
"""

from __future__ import annotations

import json
import re
import select
import socket
import socketserver
import struct
import threading
import time

import pytest

from millsense.daemon.dashboard import book as book_mod
from millsense.daemon.dashboard.book import Book
from millsense.daemon.dashboard.server import DashboardServer
from tests.e2e.helpers import wait_for

WAIT_S = 30.0  # generous: how long a test waits for something that should happen at once


@pytest.fixture
def server():
    s = DashboardServer(("127.0.0.1", 0), Book(), relay=None, https=False)
    thread = threading.Thread(target=s.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield s
    finally:
        s.stopping.set()
        for client in list(s.book.clients):
            client.close()  # an open stream's thread ends now, not at its next keep-alive
        s.shutdown()
        s.server_close()
        wait_for(lambda: not _handler_threads(), WAIT_S, "the handler threads to end")


def _handler_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if "process_request_thread" in t.name and t.is_alive()]


def _connect(server, source="127.0.0.1") -> socket.socket:
    sock = socket.socket()
    sock.bind((source, 0))
    sock.settimeout(WAIT_S)
    sock.connect(server.server_address)
    return sock


def _closed_by_server(sock: socket.socket) -> bool:
    """True once the server has closed the connection (EOF or reset), without blocking."""
    if not select.select([sock], [], [], 0)[0]:
        return False
    try:
        return sock.recv(65536) == b""
    except ConnectionError:
        return True


def _no_traceback(capfd) -> None:
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err, out + err


def test_a_request_that_does_not_arrive_whole_is_cut_off(server, capfd):
    server.request_timeout_s = 0.5
    idle = _connect(server)
    idle.sendall(b"GET / HTTP/1.1\r\n")  # never the end of the headers
    slow = _connect(server)
    slow.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Pad: ")
    deadline = time.monotonic() + WAIT_S
    while not _closed_by_server(slow):  # a byte now and then: every read is quick, the request never ends
        assert time.monotonic() < deadline, "a request dribbled a byte at a time was never cut off"
        try:
            slow.sendall(b"a")
        except ConnectionError:
            break
        time.sleep(0.05)
    assert idle.recv(65536) == b"", "an idle request was answered instead of cut off"
    idle.close()
    slow.close()
    wait_for(lambda: not _handler_threads(), WAIT_S, "their threads to end")
    _no_traceback(capfd)


def _open_events(server, source="127.0.0.1") -> tuple[socket.socket, bytes]:
    """A raw `/events` request: (socket, what came first: the head and the snapshot event, or a refusal)."""
    sock = _connect(server, source)
    sock.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    got = b""
    while not _whole(got):
        chunk = sock.recv(65536)
        assert chunk, f"closed after {got!r}"
        got += chunk
    return sock, got


def _whole(got: bytes) -> bool:
    """The head and then, for a stream, its first event; for a refusal, its JSON body."""
    head, sep, body = got.partition(b"\r\n\r\n")
    if not sep:
        return False
    if b" 200 " in head.split(b"\r\n", 1)[0]:
        return body.endswith(b"\n\n")
    return len(body) >= int(re.search(rb"Content-Length: (\d+)", head)[1])


def test_an_event_stream_outlives_the_request_deadline(server):
    """The deadline is on reading a request; a page's stream only receives, for as long as it stays open."""
    server.request_timeout_s = 0.5
    stream, first = _open_events(server)
    assert b" 200 " in first and b'"kind":"snapshot"' in first
    idle = _connect(server)  # opened after the stream: once it is cut off, the stream's deadline is past too
    idle.sendall(b"GET / HTTP/1.1\r\n")
    assert idle.recv(65536) == b"", "an idle request was answered instead of cut off"
    server.book.publication("m-1", "estimate", {"rev": 1, "t": 1.0, "torque_nm": 2.5})
    got = b""
    while b"\n\n" not in got:
        chunk = stream.recv(65536)
        assert chunk, "the event stream was cut off"
        got += chunk
    assert b'"kind":"batch"' in got and b'"torque_nm":2.5' in got
    stream.close()
    idle.close()


def test_connections_over_the_cap_are_refused_at_once_without_a_thread(server, capfd):
    server.max_connections = 4
    server.request_timeout_s = 600.0  # they stay until the test closes them, however slow this machine
    held = []
    for _ in range(4):
        s = _connect(server)
        s.sendall(b"GET / HTTP/1.1\r\n")  # unfinished
        held.append(s)
    wait_for(lambda: len(_handler_threads()) == 4, WAIT_S, "4 connections served")
    surplus = _connect(server)
    surplus.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    try:
        answer = surplus.recv(65536)
    except ConnectionError:
        answer = b""
    assert answer == b"", f"the 5th connection was served: {answer[:60]!r}"
    assert server.refused_connections == 1
    assert len(_handler_threads()) == 4  # no thread was started for it
    for s in held:
        s.close()
    wait_for(lambda: not _handler_threads(), WAIT_S, "the held connections to end")
    ok = _connect(server)
    ok.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
    assert ok.recv(65536).startswith(b"HTTP/1.1 200 "), "a connection after the flood was not served"
    ok.close()
    _no_traceback(capfd)


def test_one_peer_cannot_take_every_connection(server, capfd):
    """A buggy HMI opening half-requests over and over takes its own share of the connections, not all of them."""
    server.request_timeout_s = 600.0  # the hog's requests stay until the test closes them, however slow this machine
    server.log.interval_s = 600.0  # however slow this machine, the flood falls in one log interval
    hog = []
    try:
        for _ in range(server.max_connections):  # as many as the whole server takes
            s = _connect(server, "127.0.0.2")
            try:
                s.sendall(b"GET / HTTP/1.1\r\n")  # unfinished
            except ConnectionError:
                pass  # already closed by the server: the surplus
            hog.append(s)
        # Connections are accepted in order: by the time this one is, every one of the hog's has been.
        victim = _connect(server, "127.0.0.1")
        victim.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        try:
            answer = victim.recv(65536)
        except ConnectionError:
            answer = b""
        victim.close()
        assert answer.startswith(b"HTTP/1.1 200 "), f"another screen was refused while one peer held " \
                                                    f"{server.max_connections} half-requests: {answer[:60]!r}"
        share = server.max_connections_per_peer
        surplus = server.max_connections - share
        assert server.refused_connections == surplus
        wait_for(lambda: sum(_closed_by_server(s) for s in hog) == surplus, WAIT_S,
                 f"the hog's {surplus} surplus connections to be closed")
        # The victim's thread ends after its answer; the share's stay for the test, and none started for the surplus.
        wait_for(lambda: len(_handler_threads()) == share, WAIT_S, f"the hog's {share} connections alone served")
        assert server.peer_connections == {"127.0.0.2": share}
    finally:
        for s in hog:
            s.close()
    wait_for(lambda: not _handler_threads(), WAIT_S, "the hog's connections to end")
    assert server.connections == 0 and not server.peer_connections  # a peer gone leaves nothing behind
    again = _connect(server, "127.0.0.2")  # its share is its own again
    again.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
    assert again.recv(65536).startswith(b"HTTP/1.1 200 ")
    again.close()
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err, out + err
    refusals = [line for line in (out + err).splitlines() if "dashboard_connection_refused" in line]
    assert len(refusals) == 1 and "127.0.0.2" in refusals[0], out + err


def test_a_thread_that_cannot_start_refuses_the_connection_in_one_line(server, capfd, monkeypatch):
    """Under systemd's TasksMax (or out of memory) a thread may not start: no traceback, the client is closed."""
    def no_thread(self, request, client_address):
        raise RuntimeError("can't start new thread")  # what threading says when the task limit is reached

    monkeypatch.setattr(socketserver.ThreadingMixIn, "process_request", no_thread)
    s = _connect(server)
    s.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    try:
        assert s.recv(65536) == b""
    except ConnectionError:
        pass
    s.close()
    monkeypatch.undo()
    out, err = capfd.readouterr()  # said before the connection was closed
    assert "Traceback" not in out + err, out + err
    assert len([line for line in (out + err).splitlines() if "can't start new thread" in line]) == 1, out + err
    assert server.refused_connections == 1 and server.connections == 0


def test_one_peer_cannot_take_every_page(server):
    """A kiosk reconnecting without closing its old streams fills its own share, not everyone's."""
    per_peer, total = book_mod.MAX_CLIENTS_PER_PEER, book_mod.MAX_CLIENTS
    streams = [_open_events(server)[0] for _ in range(per_peer)]
    extra, refused = _open_events(server)
    assert b" 503 " in refused.split(b"\r\n", 1)[0], refused
    error = json.loads(refused.split(b"\r\n\r\n", 1)[1])["error"]
    assert f"{per_peer} per address" in error and "127.0.0.1" in error, error
    extra.close()
    other, first = _open_events(server, "127.0.0.2")  # another screen still gets its page
    assert b" 200 " in first
    streams.append(other)
    peer = 2
    while len(streams) < total:  # the global bound still holds, across peers
        peer += len(streams) % per_peer == 0
        streams.append(_open_events(server, f"127.0.0.{peer}")[0])
    last, refused = _open_events(server, "127.0.0.200")
    assert b" 503 " in refused.split(b"\r\n", 1)[0], refused
    assert f"{total} open" in json.loads(refused.split(b"\r\n\r\n", 1)[1])["error"]
    for s in [*streams, last]:
        s.close()


def test_a_client_that_hangs_up_early_leaves_no_traceback(server, capfd):
    """Closed plainly, the answer's second write meets a broken pipe; closed with a reset, the read fails."""
    for i in range(20):
        s = socket.socket()
        if i % 2:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.connect(server.server_address)
        s.sendall(b"GET /api/info HTTP/1.1\r\n")  # no Host: answered 421, to nobody
        s.close()
    wait_for(lambda: not _handler_threads(), WAIT_S, "their threads to end")
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err and "dashboard_request_failed" not in out + err, out + err


# -- refused requests with a body (issue 36, finding 7) ----------------------------------------------------

NEXT = b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"  # the connection's next request


def _read_answer(sock: socket.socket, got: bytes = b"") -> tuple[bytes, bytes, bytes]:
    """One whole answer (not a stream) from `sock`: (head, JSON body, what came after it)."""
    while True:
        head, sep, rest = got.partition(b"\r\n\r\n")
        if sep and len(rest) >= int(re.search(rb"Content-Length: (\d+)", head)[1]):
            break
        chunk = sock.recv(65536)
        assert chunk, f"closed after {got!r}"
        got += chunk
    length = int(re.search(rb"Content-Length: (\d+)", head)[1])
    return head, rest[:length], rest[length:]


def _post_raw(path: str, body: bytes, host: str = "127.0.0.1", headers: str = "X-Millsense: reset\r\n",
              method: str = "POST") -> bytes:
    return (f"{method} {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n{headers}"
            f"Content-Length: {len(body)}\r\n\r\n").encode() + body


STEP = json.dumps({"step": "challenge", "client_nonce": "ab" * 16}).encode()
REFUSALS = {  # what the page or another client may send that is refused, each with a body
    "403 header missing": (_post_raw("/api/reset/m-1", STEP, headers=""), 403),
    "404 another path": (_post_raw("/api/nothing", STEP), 404),
    "404 GET with a body": (_post_raw("/nothing", STEP, method="GET"), 404),
    "405 another method": (_post_raw("/api/reset/m-1", STEP, method="PUT"), 405),
    "413 a body over 4096 bytes": (_post_raw("/api/reset/m-1", b"x" * 5000), 413),
    "421 another Host": (_post_raw("/api/reset/m-1", STEP, host="attacker.example"), 421),
}


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_a_refused_request_with_a_body_leaves_the_connection_ready_for_the_next(server, case, capfd):
    request, status = REFUSALS[case]
    sock = _connect(server)
    sock.sendall(request + NEXT)  # the next request follows at once, as a browser's kept-alive connection may
    head, body, rest = _read_answer(sock)
    assert head.startswith(f"HTTP/1.1 {status} ".encode()), head
    assert json.loads(body)["ok"] is False and b"Connection: close" not in head
    head, body, _ = _read_answer(sock, rest)
    assert head.startswith(b"HTTP/1.1 200 "), (case, head, body)  # before: 501 Unsupported method ('{"step":…}GET')
    assert json.loads(body)["reset_offered"] is True
    sock.close()
    _no_traceback(capfd)


def test_a_refusal_when_the_reset_is_not_offered_drains_its_body_too():
    s = DashboardServer(("0.0.0.0", 0), Book(), relay=None, https=False)
    thread = threading.Thread(target=s.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        sock = socket.create_connection(("127.0.0.1", s.server_address[1]), timeout=WAIT_S)
        sock.sendall(_post_raw("/api/reset/m-1", STEP) + NEXT)
        head, body, rest = _read_answer(sock)
        assert head.startswith(b"HTTP/1.1 403 ") and "HTTPS" in json.loads(body)["error"]
        head, body, _ = _read_answer(sock, rest)
        assert head.startswith(b"HTTP/1.1 200 ") and json.loads(body)["reset_offered"] is False
        sock.close()
    finally:
        s.shutdown()
        s.server_close()


def test_a_body_over_64_kib_or_without_a_length_closes_the_connection(server):
    big = b"x" * (64 * 1024 + 1)
    for request, status in ((_post_raw("/api/nothing", big), 404),
                            (_post_raw("/api/reset/m-1", big, host="attacker.example"), 421),
                            (b"POST /api/reset/m-1 HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Millsense: reset\r\n"
                             b"Transfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n", 411),
                            (b"POST /api/reset/m-1 HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Millsense: reset\r\n"
                             b"Content-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n", 411)):
        sock = _connect(server)
        try:
            sock.sendall(request + NEXT)
        except ConnectionError:
            pass  # closed while the surplus was still being sent
        head, body, rest = _read_answer(sock)
        assert head.startswith(f"HTTP/1.1 {status} ".encode()) and b"Connection: close" in head, head
        assert json.loads(body)["ok"] is False
        wait_for(lambda: _closed_by_server(sock), WAIT_S, "the connection closed after the answer")
        sock.close()


def test_a_post_with_another_host_is_refused_before_anything_is_relayed(capfd):
    """DNS rebinding against the relay: a site re-pointed at 127.0.0.1 must not reach `cmd/reset` (issue 36, 9)."""
    relayed = []

    class Relay:
        def relay_reset(self, machine, request):
            relayed.append((machine, request))
            return []

    s = DashboardServer(("127.0.0.1", 0), Book(), relay=Relay(), https=False)
    thread = threading.Thread(target=s.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        sock = _connect(s)
        sock.sendall(_post_raw("/api/reset/m-1", STEP, host="rebound.example:8470"))
        head, body, rest = _read_answer(sock)
        assert head.startswith(b"HTTP/1.1 421 ") and "localhost" in json.loads(body)["error"], head
        sock.sendall(_post_raw("/api/reset/m-1", STEP, host="localhost:8470"))  # the page's own request
        head, body, _ = _read_answer(sock, rest)
        assert head.startswith(b"HTTP/1.1 200 ") and json.loads(body) == {"ok": True, "replies": []}
        assert relayed == [("m-1", {"step": "challenge", "client_nonce": "ab" * 16})]
        sock.close()
    finally:
        s.shutdown()
        s.server_close()
