"""The framed stream over a raw TCP socket (a serial-to-Ethernet converter, `millsense sim --tcp`)."""

from __future__ import annotations

import select
import socket

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

    @classmethod
    def from_options(cls, host: str = "", tcp_port: int = 0, **_ignored) -> TcpDriver:
        return cls(host, tcp_port)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.tcp_port}"

    def _open(self) -> None:
        sock = socket.create_connection((self.host, self.tcp_port), timeout=self.connect_timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(self.read_timeout_s)
        self._sock = sock

    def _close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _wait_readable(self, timeout_s: float) -> bool:
        sock = self._sock
        if sock is None:
            raise LinkDown("socket closed")
        try:
            return bool(select.select([sock], [], [], timeout_s)[0])  # a closed peer reads as readable
        except (OSError, ValueError) as exc:
            raise LinkDown(f"lost communication with DAQ at {self.address}: {exc}") from exc

    def _read_bytes(self) -> bytes:
        sock = self._sock
        if sock is None:
            raise LinkDown("socket closed")
        try:
            data = sock.recv(262144)
        except TimeoutError:
            return b""
        except OSError as exc:
            raise LinkDown(f"lost communication with DAQ at {self.address}: {exc}") from exc
        if not data:
            raise LinkDown(f"lost communication with DAQ at {self.address}: connection closed by peer")
        return data

    def _write(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            raise LinkDown("socket closed")
        sock.sendall(data)
