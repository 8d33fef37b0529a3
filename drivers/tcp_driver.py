"""The framed stream over a raw TCP socket (a serial-to-Ethernet converter, `millsense sim --tcp`).

One system call per arriving frame (issue 13): the socket is in blocking mode with the
kernel's own receive and send timeouts (SO_RCVTIMEO / SO_SNDTIMEO), so the reader
sleeps in `recv` itself. Python's own socket timeout would poll first and then
receive, and the select-then-read of the generic stream driver was a third call:
each costs tens of microseconds on the cold path of a wake-up.
"""

from __future__ import annotations

import socket
import struct
import time

from millsense.drivers.base import LinkDown, StreamDriver


class TcpDriver(StreamDriver):
    transport = "tcp"

    def __init__(
        self, host: str, tcp_port: int, *, connect_timeout_s: float = 2.0, read_timeout_s: float = 0.2, **kwargs
    ) -> None:
        super().__init__(**kwargs)
        if not host or not tcp_port:
            raise ValueError("tcp transport needs host and tcp_port")
        self.host = host
        self.tcp_port = int(tcp_port)
        self.connect_timeout_s = connect_timeout_s
        self.read_timeout_s = read_timeout_s
        self._sock: socket.socket | None = None
        self._down_next: LinkDown | None = None  # a loss found by the batched read, raised after its bytes

    @classmethod
    def from_options(cls, host: str = "", tcp_port: int = 0, **_ignored) -> TcpDriver:
        return cls(host, tcp_port)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.tcp_port}"

    def _open(self) -> None:
        # An ASCII host goes to the resolver as bytes: a str one is first run through the `idna` codec,
        # whose import alone holds 0.4 MB of the daemon's memory (issue 13). A non-ASCII name still needs it.
        host = self.host.encode("ascii") if self.host.isascii() else self.host
        sock = socket.create_connection((host, self.tcp_port), timeout=self.connect_timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(None)  # blocking: the kernel's timeouts below bound each call
        timeval = _timeval(self.read_timeout_s)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, timeval)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, timeval)
        self._down_next = None
        self._sock = sock

    def _close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _read(self) -> list:
        """What lands is read at once; only bytes landing sooner than `read_interval_s` after the
        last read wait out the rest of it and are read together with what came meanwhile (a DAQ
        sending one sample a frame wakes the reader at most 500 times a second)."""
        down, self._down_next = self._down_next, None
        if down is not None:
            raise down
        data = self._read_bytes()
        now = time.monotonic()
        if data and now - self._last_read < self.read_interval_s:
            time.sleep(self._last_read + self.read_interval_s - now)
            try:
                data += self._read_bytes(wait=False)
            except LinkDown as exc:  # the bytes read before it are decoded first; the link goes down next
                self._down_next = exc
            now = time.monotonic()
        if not data:
            return []
        self._last_read = now
        return self._decoder.feed(data)

    def _wait_readable(self, timeout_s: float) -> bool:
        return True  # `_read_bytes` waits itself, up to read_timeout_s

    def _read_bytes(self, wait: bool = True) -> bytes:
        sock = self._sock
        if sock is None:
            raise LinkDown("socket closed")
        try:
            data = sock.recv(262144) if wait else sock.recv(262144, socket.MSG_DONTWAIT)
        except BlockingIOError:  # SO_RCVTIMEO ran out (or, not waiting, nothing there): the loop looks up
            return b""
        except OSError as exc:
            raise LinkDown(f"lost communication with DAQ at {self.address}: {exc}") from exc
        if not data and wait:
            raise LinkDown(f"lost communication with DAQ at {self.address}: connection closed by peer")
        return data  # not waiting, an end of stream reads as nothing: the next read raises, after these bytes

    def _write(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            raise LinkDown("socket closed")
        sock.sendall(data)


def _timeval(seconds: float) -> bytes:
    """A `struct timeval` for SO_RCVTIMEO / SO_SNDTIMEO."""
    whole = int(seconds)
    return struct.pack("@ll", whole, int(round((seconds - whole) * 1e6)))
