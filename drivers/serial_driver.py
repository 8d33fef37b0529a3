"""The framed stream over a serial port (USB-CDC, RS-422), or any URL pyserial accepts.

The reader waits in `select` on the port's file descriptor and, once bytes
are there, reads them without waiting (timeout 0): one wake-up per frame,
and a frame is handed on as soon as it lands. A port without a file
descriptor (pyserial's `loop://` and the like) falls back to reads with a
10 ms timeout. ``in_waiting`` is not used: on ``socket://`` ports it is only
0 or 1. ``socket://host:port`` and other pyserial URLs work as ports.
"""

from __future__ import annotations

import os
import select

from millsense.drivers.base import LinkDown, StreamDriver


class SerialDriver(StreamDriver):
    transport = "serial"
    READ_SIZE = 65536

    def __init__(self, port: str, baudrate: int = 921600, *, read_timeout_s: float = 0.01, **kwargs) -> None:
        super().__init__(**kwargs)
        if not port:
            raise ValueError("serial transport needs a port")
        self.port = port
        self.baudrate = int(baudrate)
        self.read_timeout_s = read_timeout_s
        self._serial = None
        self._fd: int | None = None  # what select waits on; None: reads wait read_timeout_s instead

    @classmethod
    def from_options(cls, port: str = "", baudrate: int = 921600, **_ignored) -> SerialDriver:
        return cls(port, baudrate)

    @property
    def address(self) -> str:
        return self.port

    def _open(self) -> None:
        import serial

        try:
            self._serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, timeout=self.read_timeout_s, write_timeout=1.0
            )
        except (serial.SerialException, ValueError) as exc:
            raise LinkDown(f"cannot open {self.port}: {_why(exc)}") from exc
        # bytes that waited in the port while nobody read are stale: start fresh
        self._serial.reset_input_buffer()
        try:
            self._fd = int(self._serial.fileno())
        except (AttributeError, NotImplementedError, OSError, ValueError, TypeError):
            self._fd = None
        if self._fd is not None:
            self._serial.timeout = 0  # select does the waiting; a read takes what is there

    def _close(self) -> None:
        ser, self._serial, self._fd = self._serial, None, None
        if ser is not None:
            ser.close()

    def _wait_readable(self, timeout_s: float) -> bool:
        if self._serial is None:
            raise LinkDown("port closed")
        if self._fd is None:
            return True  # the read itself waits up to read_timeout_s
        try:
            return bool(select.select([self._fd], [], [], timeout_s)[0])  # a vanished device reads as readable
        except (OSError, ValueError) as exc:
            raise LinkDown(f"lost communication with DAQ at {self.port}: {exc}") from exc

    def _read_bytes(self) -> bytes:
        import serial

        ser = self._serial
        if ser is None:
            raise LinkDown("port closed")
        try:
            return ser.read(self.READ_SIZE)
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise LinkDown(f"lost communication with DAQ at {self.port}: {exc}") from exc

    def _write(self, data: bytes) -> None:
        ser = self._serial
        if ser is None:
            raise LinkDown("port closed")
        ser.write(data)


def _why(exc: Exception) -> str:
    """The cause without the port's name: pyserial says "could not open port P: [Errno 2] ...: 'P'",
    which after our "cannot open P" names it three times."""
    errno = getattr(exc, "errno", None)
    if isinstance(errno, int):
        return os.strerror(errno)
    return str(exc)
