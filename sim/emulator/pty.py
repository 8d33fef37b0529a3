"""Pseudo-terminals for the emulator: a serial port with no hardware behind it.

``Pty`` is one raw pty whose slave is reachable at a stable symlink (the stream
transport, read by the daemon's serial driver). ``PtyBridge`` joins two raw ptys
back to back, as a null-modem cable joins two serial ports: pymodbus' RTU server
opens one end by its path and the daemon opens the other through the link, and
the asyncio loop copies bytes between the two masters.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import termios
import tty


def _raw(fd: int) -> None:
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[3] &= ~termios.ECHO
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class Pty:
    """A pseudo-terminal whose slave is reachable at a stable symlink ``link``.

    The emulator keeps its own descriptor of the slave open, so a reader closing
    the port does not hang the master up (no EIO) and a new reader can open it again.
    """

    def __init__(self, link: str) -> None:
        self.link = link
        self.master, self._slave = os.openpty()
        _raw(self._slave)
        os.set_blocking(self.master, False)
        name = os.ttyname(self._slave)
        tmp = f"{link}.tmp{os.getpid()}"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        try:
            os.symlink(name, tmp)
            os.replace(tmp, link)  # atomic: a reader never sees the link missing or half-made
        except OSError as exc:
            self.close()
            raise OSError(f"cannot make the pty link {link}: {exc.strerror}") from exc
        self.dropped_bytes = 0

    def write(self, data: bytes) -> None:
        try:
            n = os.write(self.master, data)
        except BlockingIOError:
            n = 0
        except OSError:
            n = 0
        self.dropped_bytes += len(data) - n

    def close(self) -> None:
        with contextlib.suppress(OSError):
            if os.path.islink(self.link) and os.readlink(self.link) == os.ttyname(self._slave):
                os.unlink(self.link)
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class PtyBridge:
    """Two raw ptys joined master to master: ``inner_path`` for a server, ``link`` for the daemon.

    Bytes are copied in the running asyncio loop (``start``), each direction as it
    arrives; a side that cannot take them loses them, as a serial line would.
    """

    def __init__(self, link: str) -> None:
        self.outer = Pty(link)
        self._inner_master, self._inner_slave = os.openpty()
        _raw(self._inner_slave)
        os.set_blocking(self._inner_master, False)
        self.inner_path = os.ttyname(self._inner_slave)
        self.link = link

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        loop.add_reader(self.outer.master, self._copy, self.outer.master, self._inner_master)
        loop.add_reader(self._inner_master, self._copy, self._inner_master, self.outer.master)

    @staticmethod
    def _copy(src: int, dst: int) -> None:
        try:
            data = os.read(src, 4096)
        except (BlockingIOError, OSError):
            return
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(dst, data)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            loop = asyncio.get_running_loop()
            loop.remove_reader(self.outer.master)
            loop.remove_reader(self._inner_master)
        self.outer.close()
        for fd in (self._inner_master, self._inner_slave):
            with contextlib.suppress(OSError):
                os.close(fd)
