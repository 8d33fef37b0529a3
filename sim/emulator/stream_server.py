"""Serves the framed stream: on a pseudo-terminal, to TCP clients, or into a capture file.

One asyncio loop does everything (pacing, writing, reading commands, the
watchdog timer), so the device model is never touched from two threads.  A
reader that cannot keep up loses bytes, as on a real serial line: writes never
block the device.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time

from millsense.sim.emulator.pacing import CncTimer
from millsense.sim.emulator.pty import Pty
from millsense.drivers.protocol import CMD_SEND_DESCRIPTOR, Command, StreamDecoder

MAX_CLIENT_BACKLOG = 1 << 20


class StreamServer:
    """Runs the device, sending frames to every sink and obeying commands from any."""

    def __init__(self, device, emitter, pacer, *, duration_samples: int | None = None, wait_client=None) -> None:
        self.device = device
        # None: the stream runs from the start; else called when the first TCP client connects, from which the
        # first sample is due (a part played whole to a daemon that connects after the emulator is up)
        self.wait_client = wait_client
        self._first_client = asyncio.Event()
        self.emitter = emitter
        self.pacer = pacer
        self.duration_samples = duration_samples
        self._writers: list = []  # callables taking bytes
        self._clients: set[asyncio.StreamWriter] = set()
        self._pty: Pty | None = None
        self._capture = None
        self._tcp_server: asyncio.AbstractServer | None = None
        self.stop = asyncio.Event()
        self.client_dropped_bytes = 0
        self._cnc = CncTimer(device, lambda now: self._send(self.emitter.context(now)))  # a CONTEXT on each change

    # -- sinks ----------------------------------------------------------------

    def open_pty(self, link: str) -> None:
        self._pty = Pty(link)
        decoder = StreamDecoder()
        loop = asyncio.get_running_loop()

        def readable() -> None:
            try:
                data = os.read(self._pty.master, 4096)
            except (BlockingIOError, OSError):
                return
            self._on_bytes(decoder, data)

        loop.add_reader(self._pty.master, readable)
        self._writers.append(self._pty.write)

    async def open_tcp(self, host: str, port: int) -> None:
        self._tcp_server = await asyncio.start_server(self._client, host, port)
        self._writers.append(self._broadcast_clients)

    def open_capture(self, fh) -> None:
        self._capture = fh
        self._writers.append(fh.write)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        # each client gets the stream from its connect on, starting with a descriptor
        writer.write(self.emitter.descriptor(time.monotonic()))
        self._clients.add(writer)
        self._first_client.set()
        decoder = StreamDecoder()
        try:
            while not self.stop.is_set():
                data = await reader.read(4096)
                if not data:
                    break
                self._on_bytes(decoder, data)
        except (ConnectionError, OSError):
            pass
        finally:
            self._clients.discard(writer)
            writer.close()

    def _broadcast_clients(self, data: bytes) -> None:
        for w in list(self._clients):
            if w.transport.is_closing():
                self._clients.discard(w)
            elif w.transport.get_write_buffer_size() > MAX_CLIENT_BACKLOG:
                self.client_dropped_bytes += len(data)
            else:
                w.write(data)

    def _send(self, data: bytes) -> None:
        if data:
            for write in self._writers:
                write(data)

    # -- commands -------------------------------------------------------------

    def _on_bytes(self, decoder: StreamDecoder, data: bytes) -> None:
        now = time.monotonic()
        # commands need no descriptor: decode them with a decoder that has none
        for frame in decoder.feed(data):
            if not isinstance(frame, Command):
                continue
            if frame.command == CMD_SEND_DESCRIPTOR:
                self._send(self.emitter.descriptor(now))
            self.device.apply_command(frame, now)
            self._send(self.emitter.status(now))  # a STATUS in reply to every command
            self._arm_watchdog()
            self._cnc.arm()

    def _arm_watchdog(self) -> None:
        deadline = self.device.watchdog_deadline()
        if deadline is None:
            return
        loop = asyncio.get_running_loop()
        loop.call_at(deadline + 0.0005, self._watchdog_check)

    def _watchdog_check(self) -> None:
        now = time.monotonic()
        if self.device.check_watchdog(now):
            self._send(self.emitter.status(now))  # the output changed
            self._cnc.arm()

    # -- main loop ------------------------------------------------------------

    async def run(self) -> None:
        if self.wait_client is not None:
            stop = asyncio.ensure_future(self.stop.wait())
            await asyncio.wait([stop, asyncio.ensure_future(self._first_client.wait())],
                               return_when=asyncio.FIRST_COMPLETED)
            if self.stop.is_set():
                await self.close()
                return
            stop.cancel()
            self.pacer.restart()
            self.wait_client()
        now = time.monotonic()
        self._send(self.emitter.descriptor(now))
        try:
            while not self.stop.is_set():
                now = time.monotonic()
                n = self.pacer.due(now, self.duration_samples)
                if not self.pacer.realtime:  # fast: periodic frames follow sample time
                    now = self.pacer.t0 + self.pacer.produced / self.pacer.rate
                # the periodic DESCRIPTOR and CONTEXT before the block is made: its CONTEXT is the one that
                # holds at the block's first sample, and the block's own changes follow in stream order
                periodic = self.emitter.periodic(now)
                if n:
                    first, counts = self.device.produce(n)
                    # a STATUS after each frame in which the CNC's applied override moved, within the block
                    self._send(periodic + self.emitter.block(first, counts, now))
                else:
                    self._send(periodic)
                if self.duration_samples is not None and self.pacer.produced >= self.duration_samples:
                    break
                if self.pacer.realtime:
                    # a plain sleep: the stop flag is seen within one batch (10 ms)
                    await asyncio.sleep(max(0.0, self.pacer.next_time() - time.monotonic()))
                else:
                    await asyncio.sleep(0)
        finally:
            await self.close()

    async def close(self) -> None:
        if self._tcp_server is not None:
            self._tcp_server.close()
            for w in list(self._clients):
                w.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._tcp_server.wait_closed(), 1.0)
            self._tcp_server = None
        if self._pty is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(self._pty.master)
            self._pty.close()
            self._pty = None
