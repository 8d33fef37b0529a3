"""The framed stream over a serial port (USB-CDC, RS-422), or any URL pyserial accepts.

Each read asks for a large block with a 10 ms timeout: it returns after at most
10 ms with whatever arrived, so the reader wakes about a hundred times a second
and never spins.  (``in_waiting`` is not used: on ``socket://`` ports it is only
0 or 1.)  ``socket://host:port`` and other pyserial URLs work as ports.
"""

from __future__ import annotations

from millsense.drivers.base import LinkDown, StreamDriver


class SerialDriver(StreamDriver):
    transport = "serial"
    read_interval_s = 0.0  # the read timeout paces the reader
    READ_SIZE = 65536

    def __init__(self, port: str, baudrate: int = 921600, *, read_timeout_s: float = 0.01, **kwargs) -> None:
        super().__init__(**kwargs)
        if not port:
            raise ValueError("serial transport needs a port")
        self.port = port
        self.baudrate = int(baudrate)
        self.read_timeout_s = read_timeout_s
        self._serial = None

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
            raise LinkDown(f"cannot open {self.port}: {exc}") from exc
        # bytes that waited in the port while nobody read are stale: start fresh
        self._serial.reset_input_buffer()

    def _close(self) -> None:
        ser, self._serial = self._serial, None
        if ser is not None:
            ser.close()

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
