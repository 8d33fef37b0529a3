"""Faults on a real TCP link: proxies that a test puts between the daemon and the emulator.

`StreamProxy` carries the framed stream (the daemon's `transport = "tcp"`, as a
serial-to-Ethernet converter would) and can cut the link, refuse connections
for a while, or splice the daemon's connection over to another emulator
mid-stream. It decodes what it forwards to the daemon with the real
`StreamDecoder`, so a test knows exactly which samples went down the wire.

`ModbusProxy` carries Modbus TCP and can answer requests with an exception
response instead of the server's, swallow responses (the client times out)
or hold everything for a while, by function code.

Everything is plain sockets and threads on 127.0.0.1; `close()` stops it all.
"""

from __future__ import annotations

import contextlib
import select
import socket
import struct
import threading
import time
from collections.abc import Callable

from millsense.drivers.protocol import Descriptor, Samples, StreamDecoder


def _listener(port: int = 0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind(("127.0.0.1", port))
    s.listen(8)
    s.settimeout(0.05)
    return s


def _close(sock: socket.socket | None) -> None:
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            sock.close()


class SampleTap:
    """What went down to the daemon, per connection: samples by device index, descriptors."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.connections: list[dict] = []  # {"first": index, "next": index, "samples": n, "channels": C}
        self.descriptors: list[Descriptor] = []
        self._decoder: StreamDecoder | None = None

    def new_connection(self) -> None:
        with self.lock:
            self._decoder = StreamDecoder()
            self.connections.append({"first": None, "next": None, "samples": 0, "frames": []})

    def feed(self, data: bytes) -> None:
        with self.lock:
            if self._decoder is None:
                return
            conn = self.connections[-1]
            for f in self._decoder.feed(data):
                if isinstance(f, Samples):
                    n = len(f.counts)
                    if conn["first"] is None:
                        conn["first"] = f.first_index
                    conn["next"] = (f.first_index + n) % (1 << 32)
                    conn["samples"] += n
                    conn["frames"].append((f.first_index, n, f.counts.shape[1]))
                elif isinstance(f, Descriptor):
                    self.descriptors.append(f)

    def summary(self) -> list[dict]:
        with self.lock:
            return [dict(c) for c in self.connections]

    def decoder_stats(self) -> dict[str, int]:
        """The counters of the decoder of the current connection (the daemon's decoder saw the same bytes)."""
        with self.lock:
            return self._decoder.stats.as_dict() if self._decoder is not None else {}


class _Pair:
    """One proxied connection: the daemon's socket, the emulator's, and a lock that keeps a
    cut from landing in the middle of a forwarded chunk (so the tap saw exactly what was sent)."""

    def __init__(self, down: socket.socket, up: socket.socket) -> None:
        self.down = down
        self.up = up
        self.send_lock = threading.Lock()
        self.alive = True


class StreamProxy:
    """127.0.0.1:<port> → upstream emulator, one upstream connection per downstream client."""

    def __init__(self, upstream_port: int, *, tap: SampleTap | None = None) -> None:
        self.upstream_port = upstream_port
        self.tap = tap or SampleTap()
        self._listen: socket.socket | None = _listener()
        self.port = self._listen.getsockname()[1]
        self._lock = threading.Lock()
        self._pairs: list[_Pair] = []
        self._stop = threading.Event()
        self.accepted = 0
        self.cuts = 0
        self._threads = [threading.Thread(target=self._accept_loop, daemon=True)]
        self._threads[0].start()

    # -- faults -------------------------------------------------------------
    def cut(self) -> int:
        """End every connection now (the converter lost its line): whatever was forwarded is
        delivered, then end of stream. Returns how many connections were cut."""
        with self._lock:
            pairs, self._pairs = self._pairs, []
        for pair in pairs:
            with pair.send_lock:
                pair.alive = False
                with contextlib.suppress(OSError):
                    pair.down.shutdown(socket.SHUT_WR)  # FIN after the data already sent
                _close(pair.up)
            # closed a little later: closing with unread bytes (heartbeats) would send RST
            threading.Timer(1.0, _close, args=(pair.down,)).start()
        if pairs:
            self.cuts += 1
        return len(pairs)

    def refuse(self, refusing: bool) -> None:
        """While refusing, nothing listens on the port (connection refused), as a converter that is off."""
        with self._lock:
            if refusing and self._listen is not None:
                _close(self._listen)
                self._listen = None
            elif not refusing and self._listen is None:
                self._listen = _listener(self.port)

    def splice(self, new_upstream_port: int, *, drop_first_s: float = 0.3) -> None:
        """Carry the open connection over to another emulator without a break downstream.

        The new emulator's greeting (a DESCRIPTOR) and whatever it sends in the
        first `drop_first_s` are dropped, so the daemon sees its SAMPLES before
        its next once-a-second DESCRIPTOR: a device whose channel count changed
        under a running stream.
        """
        up = socket.create_connection(("127.0.0.1", new_upstream_port), timeout=2.0)
        deadline = time.monotonic() + drop_first_s
        up.settimeout(0.05)
        while time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError, socket.timeout):
                if not up.recv(65536):
                    raise ConnectionError("the new upstream closed")
        up.setblocking(False)
        with self._lock:
            self.upstream_port = new_upstream_port
            pairs = list(self._pairs)
        if not pairs:
            _close(up)
            raise ConnectionError("no connection to splice")
        pair = pairs[-1]
        with pair.send_lock:
            old, pair.up = pair.up, up
        _close(old)

    # -- plumbing -----------------------------------------------------------
    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                listen = self._listen
            if listen is None:
                time.sleep(0.01)
                continue
            try:
                down, _ = listen.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                time.sleep(0.01)  # closed by refuse(); the loop picks up the new one
                continue
            try:
                up = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=2.0)
            except OSError:
                _close(down)
                continue
            down.setblocking(False)
            up.setblocking(False)
            pair = _Pair(down, up)
            self.tap.new_connection()
            with self._lock:
                self._pairs.append(pair)
                self.accepted += 1
            t = threading.Thread(target=self._pump, args=(pair,), daemon=True)
            t.start()
            self._threads.append(t)

    def _pump(self, pair: _Pair) -> None:
        while not self._stop.is_set() and pair.alive:
            down, up = pair.down, pair.up
            try:
                readable, _, _ = select.select([down, up], [], [], 0.05)
            except (OSError, ValueError):
                if pair.alive and pair.up is up:
                    self._drop(pair)
                    return
                continue  # spliced or cut meanwhile
            for s in readable:
                with pair.send_lock:
                    if not pair.alive:
                        return
                    if s is not pair.down and s is not pair.up:
                        continue  # spliced away meanwhile
                    try:
                        data = s.recv(65536)
                    except BlockingIOError:
                        continue
                    except OSError:
                        data = b""
                    if not data:
                        self._drop(pair, locked=True)
                        return
                    to_daemon = s is pair.up
                    target = pair.down if to_daemon else pair.up
                    try:
                        target.settimeout(5.0)  # a reader that stopped reading: give up, do not hang
                        target.sendall(data)
                        target.setblocking(False)
                    except OSError:
                        self._drop(pair, locked=True)
                        return
                    if to_daemon:
                        self.tap.feed(data)

    def _drop(self, pair: _Pair, locked: bool = False) -> None:
        with self._lock:
            if pair in self._pairs:
                self._pairs.remove(pair)
        pair.alive = False
        _close(pair.down)
        _close(pair.up)

    def close(self) -> None:
        self._stop.set()
        self.cut()
        self.refuse(True)
        for t in self._threads:
            t.join(1.0)


# --------------------------------------------------------------------------- Modbus
MBAP = struct.Struct(">HHHB")  # transaction id, protocol id, length (unit + PDU), unit id


def _frames(buf: bytearray) -> list[bytes]:
    """Cut whole MBAP frames off the front of `buf`."""
    out = []
    while len(buf) >= 7:
        length = struct.unpack_from(">H", buf, 4)[0]
        end = 6 + length
        if len(buf) < end:
            break
        out.append(bytes(buf[:end]))
        del buf[:end]
    return out


class ModbusProxy:
    """Modbus TCP between the daemon and the emulator, with faults by function code.

    `fail(fc, n, code)` answers the next `n` requests with function code `fc`
    with an exception response (code 4: server device failure) instead of
    passing them on; `swallow(fc, n)` passes them on but never delivers the
    answer (the client times out); `late(fc, n, seconds)` delivers the answer
    that much later (after the client gave up, into its next request's wait);
    `hold(seconds)` forwards nothing either way for that long and then drops
    what was held. `requests` counts what passed; `arrivals` lists every request in order.
    """

    def __init__(self, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self._listen = _listener()
        self.port = self._listen.getsockname()[1]
        self._lock = threading.Lock()
        self._fail: dict[int, list[int]] = {}  # fc -> [remaining, code]
        self._swallow: dict[int, int] = {}
        self._late: dict[int, list[float]] = {}  # fc -> [remaining, delay_s]
        self._send_lock = threading.Lock()
        self._hold_until = 0.0
        self.injected: list[tuple[float, int, str]] = []  # (monotonic, fc, "exception" | "swallowed" | "late" | "held")
        self.requests: dict[int, int] = {}
        self.arrivals: list[tuple[float, int]] = []  # (monotonic, fc) of every request, in order
        self.connections = 0
        self._socks: list[socket.socket] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept_loop, daemon=True)
        self._thread.start()

    def fail(self, fc: int, n: int = 1, code: int = 4) -> None:
        with self._lock:
            self._fail[fc] = [n, code]

    def swallow(self, fc: int, n: int = 1) -> None:
        with self._lock:
            self._swallow[fc] = n

    def late(self, fc: int, n: int = 1, seconds: float = 0.3) -> None:
        with self._lock:
            self._late[fc] = [n, seconds]

    def _send_down(self, down: socket.socket, frame: bytes) -> None:
        try:
            with self._send_lock:
                down.sendall(frame)
        except OSError:
            pass

    def hold(self, seconds: float) -> None:
        with self._lock:
            self._hold_until = time.monotonic() + seconds

    def injected_count(self, kind: str, fc: int | None = None) -> int:
        with self._lock:
            return sum(1 for _, f, k in self.injected if k == kind and (fc is None or f == fc))

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                down, _ = self._listen.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            try:
                up = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=2.0)
            except OSError:
                _close(down)
                continue
            with self._lock:
                self.connections += 1
                self._socks += [down, up]
            threading.Thread(target=self._pump, args=(down, up), daemon=True).start()

    def _pump(self, down: socket.socket, up: socket.socket) -> None:
        from_client, from_server = bytearray(), bytearray()
        pending: dict[int, tuple[int, str | None]] = {}  # tid -> (fc, fate of its answer)
        try:
            while not self._stop.is_set():
                readable, _, _ = select.select([down, up], [], [], 0.05)
                for s in readable:
                    data = s.recv(65536)
                    if not data:
                        return
                    held = time.monotonic() < self._hold_until
                    if s is down:
                        from_client += data
                        for frame in _frames(from_client):
                            self._request(frame, down, up, pending, held)
                    else:
                        from_server += data
                        for frame in _frames(from_server):
                            tid = MBAP.unpack_from(frame)[0]
                            fc, fate = pending.pop(tid, (frame[7], None))
                            if held or fate == "swallow":
                                continue
                            if isinstance(fate, float):  # late: delivered after the client's timeout
                                threading.Timer(fate, self._send_down, (down, frame)).start()
                                continue
                            self._send_down(down, frame)
        except OSError:
            return
        finally:
            _close(down)
            _close(up)

    def _request(self, frame: bytes, down, up, pending: dict, held: bool) -> None:
        tid, _, _, unit = MBAP.unpack_from(frame)
        fc = frame[7]
        now = time.monotonic()
        with self._lock:
            self.requests[fc] = self.requests.get(fc, 0) + 1
            self.arrivals.append((now, fc))
            fail = self._fail.get(fc)
            if held:
                self.injected.append((now, fc, "held"))
                return
            if fail and fail[0] > 0:
                fail[0] -= 1
                self.injected.append((now, fc, "exception"))
                code = fail[1]
            else:
                code = None
                late = self._late.get(fc)
                if self._swallow.get(fc, 0) > 0:
                    self._swallow[fc] -= 1
                    self.injected.append((now, fc, "swallowed"))
                    pending[tid] = (fc, "swallow")
                elif late and late[0] > 0:
                    late[0] -= 1
                    self.injected.append((now, fc, "late"))
                    pending[tid] = (fc, float(late[1]))
                else:
                    pending[tid] = (fc, None)
        if code is not None:
            self._send_down(down, MBAP.pack(tid, 0, 3, unit) + bytes([fc | 0x80, code]))
        else:
            up.sendall(frame)

    def close(self) -> None:
        self._stop.set()
        _close(self._listen)
        with self._lock:
            socks = list(self._socks)
        for s in socks:
            _close(s)
        self._thread.join(1.0)


def wait_until(predicate: Callable[[], object], timeout_s: float, what: str, step_s: float = 0.02):
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s: {what}")
        time.sleep(step_s)
