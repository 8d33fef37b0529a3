"""Modbus TCP / RTU: reads the device's sample ring as daq-protocol.md describes.

Each poll: read the head H, read whole samples from where we are up to H in
chunks of at most 125 registers (split where the ring wraps), read the head
again; samples k < H_after - D may have been overwritten while we read and are
dropped (the index gap makes them count as lost).  A reader more than D behind
resumes half a second (at most D/2) after H - D, so that what it reads is not overwritten
while it reads, and the skipped samples are lost the same way.  A poll hands over what it
read after READ_SLICE_S and the next poll goes on at once: a reader behind by seconds (after
an outage, or slowed by a loaded box or a slow gateway) still hands samples over as it goes.

pymodbus clients are not thread-safe, so every request holds the I/O lock;
outputs from other threads slip in between ring chunks.

A request that goes unanswered or garbled (noise on an RS-485 line, a busy
gateway) is sent again, up to `ATTEMPTS` times, before the link counts as
down: one bad frame must not raise `daq_lost`. Each try waits at most
`timeout_ms` (default 200) with the I/O lock released in between, so a
heartbeat still gets out while a request hangs; the config check keeps
`timeout_ms` below the interlock's `watchdog_ms − heartbeat_ms`. An exception
response saying the register map is wrong (illegal function, address or value)
is not retried: it would only fail again.

The link is up once the DAQ has answered, not once the port opened: `_connect`
reads the descriptor (a serial port opens with nothing behind it; a gateway
takes the TCP connection whatever its serial side does). A DAQ that never
answers (wrong unit id or baud rate, a broken RS-485 pair) is then a connect
failure, said once with what to check and tried again quietly with the base's
doubling back-off, not a link that comes and goes every second.

Protocol version 2 (input register 0 = 2): each poll reads registers 0–15 in
one request where version 1 reads the head (4–5), so the feed override applied
(6) and the context (8–15) cost no extra request. A context that changed
becomes a ``Context`` event; a changed override a fresh ``Status``. Registers
0–3 are checked on every poll: a device that comes back with another layout is
read again from its descriptor. Discrete input 1 (watchdog tripped) is read too.
"""

from __future__ import annotations

import select
import socket
import threading
import time

import numpy as np

from millsense.drivers.base import CommandRefused, Driver, LinkDown, log
from millsense.drivers.protocol import (
    FLAG_WATCHDOG,
    INDEX_MOD,
    OUT_ALARM_LAMP,
    OUT_FEED_HOLD,
    Channel,
    ChannelKind,
    Context,
    Descriptor,
    Samples,
    Status,
)

RING_BASE = 1000
CHANNEL_TABLE = 16
MAX_REGS = 125
HR_HEARTBEAT = 100
HR_WATCHDOG = 101
HR_FEED_OVERRIDE = 102  # version 2
IR_OVERRIDE = 6  # version 2: 6 override applied, 7 capabilities, 8-15 context
V2_HEAD_REGS = 16  # version 2: registers 0-15 in one read each poll
STATUS_PERIOD_S = 0.1
ATTEMPTS = 3  # tries of one request before the link counts as down
RETRY_PAUSE_S = 0.02  # between tries, outside the I/O lock (see `_call`)
# A poll hands over what it has read after this long and the next poll goes on at once: behind by
# seconds (after an outage, or on a loaded box where each request waits for the CPU), reading the
# whole backlog first would keep every sample from the pipeline for as long, and the pipeline
# would take the silence for a stalled DAQ (drivers/base.py: `_read` returns within ~0.2 s).
READ_SLICE_S = 0.1
OVERRUN_MARGIN_S = 0.5  # a reader more than the ring behind skips this much more than it must
DEFAULT_TIMEOUT_MS = 200
PERMANENT_EXCEPTION_CODES = frozenset({1, 2, 3})  # illegal function / data address / data value
GATEWAY_NO_ANSWER_CODES = frozenset({10, 11})  # gateway path unavailable / target device failed to respond


class NoAnswer(LinkDown):
    """Every try of a request went unanswered by the DAQ: silence, or its gateway saying so.
    ``how`` says which, for a message: "within 200 ms", "(the gateway answered exception 11)"."""

    def __init__(self, message: str, how: str) -> None:
        super().__init__(message)
        self.how = how


class ModbusDriver(Driver):
    def __init__(self, *, unit: int = 1, poll_ms: int = 20, timeout_ms: int = DEFAULT_TIMEOUT_MS, **kwargs) -> None:
        super().__init__(**kwargs)
        # `_connect` (run under the I/O lock) reads the descriptor through `_call`, which takes it too;
        # no other thread waits for it then: commands are not sent while the link is down
        self._io_lock = threading.RLock()
        self.unit = int(unit)
        self.poll_s = max(1, int(poll_ms)) / 1000.0
        self.timeout_s = max(1, int(timeout_ms)) / 1000.0
        self._client = None
        self._next: int | None = None  # device index of the next sample to read
        self._ring_depth = 0
        self._channels = 0
        self._want_descriptor = True
        self._next_poll = 0.0
        self._watchdog_ms: int | None = None
        self._just_connected = False
        self._next_status = 0.0
        self._layout: tuple[int, ...] | None = None  # registers 0-3 as the descriptor read them
        self._v2 = False
        self._override: int | None = None  # input register 6, from the last poll (version 2)
        self._context_regs: tuple[int, ...] | None = None
        self._answered: Descriptor | None = None  # read by `_connect`, handed over by the first `_read`

    # -- transport-specific -------------------------------------------------

    def _make_client(self):
        raise NotImplementedError

    @staticmethod
    def _quiet_pymodbus() -> None:
        """pymodbus logs an ERROR on every failed connect; the driver's own one event per
        link change says it once, with the transport and address."""
        import logging

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    def _silent(self, how: str) -> str:
        """Why a connect failed when the port opened but the DAQ said nothing (``how``: "within 200 ms (3 tries)")."""
        raise NotImplementedError

    # -- requests -----------------------------------------------------------

    def _call(self, fn, *args, **kwargs):
        """One request under the I/O lock, tried up to `ATTEMPTS` times; then the link is down."""
        from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

        unanswered, how = 0, ""  # tries the DAQ did not answer: a timeout, or its gateway saying it got no answer
        for attempt in range(1, ATTEMPTS + 1):
            with self._io_lock:
                client = self._client
                if client is None:
                    raise LinkDown("not connected")
                try:
                    rr = fn(client, *args, device_id=self.unit, **kwargs)
                except ConnectionException as exc:  # the socket or port is gone: no point asking again
                    raise LinkDown(f"lost communication with DAQ at {self.address}: {exc}") from exc
                except ModbusIOException:  # pymodbus' "no response received": nothing valid in time
                    problem = f"no answer from DAQ at {self.address} within {self.timeout_s * 1e3:.0f} ms"
                    unanswered, how = unanswered + 1, f"within {self.timeout_s * 1e3:.0f} ms"
                    self._discard_late_answer(client)
                except (ModbusException, OSError) as exc:  # a garbled answer
                    problem = f"lost communication with DAQ at {self.address}: {exc}"
                    self._discard_late_answer(client)
                else:
                    if not rr.isError():
                        self._stats["modbus_requests"] += 1
                        return rr
                    problem = f"DAQ at {self.address} refused a request: {rr}"
                    code = getattr(rr, "exception_code", None)
                    if code in PERMANENT_EXCEPTION_CODES:
                        raise LinkDown(problem)
                    if code in GATEWAY_NO_ANSWER_CODES:
                        unanswered, how = unanswered + 1, f"(the gateway answered exception {code})"
            if attempt < ATTEMPTS:
                self._stats["modbus_retries"] += 1
                log.debug("modbus request retried", transport=self.transport, attempt=attempt, problem=problem)
                # a heartbeat waiting for the lock through this try goes before the next one: a lock
                # is not handed over on release, and the retry would take it straight back
                time.sleep(RETRY_PAUSE_S)
        if unanswered == ATTEMPTS:
            raise NoAnswer(f"{problem} ({ATTEMPTS} tries)", f"{how} ({ATTEMPTS} tries)")
        raise LinkDown(f"{problem} ({ATTEMPTS} tries)")

    @staticmethod
    def _discard_late_answer(client) -> None:
        """A TCP answer that comes after its timeout would be taken for the next request's: drop it.

        (pymodbus' serial client already empties its receive buffer before each request.)
        """
        sock = getattr(client, "socket", None)
        if not isinstance(sock, socket.socket):
            return
        try:
            while select.select([sock], [], [], 0)[0]:
                if not sock.recv(4096):
                    break
        except OSError:
            pass

    def _input(self, address: int, count: int) -> list[int]:
        regs = self._call(lambda c, **kw: c.read_input_registers(address, count=count, **kw)).registers
        if len(regs) != count:  # a malformed answer: never guess which registers these are
            raise LinkDown(
                f"DAQ at {self.address} answered {len(regs)} registers to a read of {count} at {address}"
            )
        return regs

    def _bits(self, rr, count: int, what: str) -> list[bool]:
        bits = list(rr.bits)
        if len(bits) < count:
            raise LinkDown(f"DAQ at {self.address} answered {len(bits)} bits to a read of {count} {what}")
        return bits[:count]

    def _head(self) -> int:
        hi, lo = self._input(4, 2)
        return (hi << 16) | lo

    def _connect(self) -> None:
        self._quiet_pymodbus()
        client = self._make_client()
        if not client.connect():
            client.close()
            raise LinkDown(f"cannot connect to DAQ at {self.address}")
        self._client = client
        try:  # the link is up once the DAQ has answered: its descriptor, handed over by the first `_read`
            self._answered = self._read_descriptor()
        except NoAnswer as exc:
            self._disconnect()
            raise LinkDown(self._silent(exc.how)) from exc
        except BaseException:
            self._disconnect()
            raise
        # keep _next: if the device kept counting, what is still in its ring is
        # read back after a reconnect instead of being lost
        self._just_connected = True
        self._want_descriptor = False

    def _disconnect(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    def _after_connect(self) -> None:
        if self._watchdog_ms is not None:
            self._send_watchdog(self._watchdog_ms)

    def _read_descriptor(self) -> Descriptor:
        version, c, rate, depth = self._input(0, 4)
        if not 1 <= c <= 125 or depth < 1 or rate < 1:
            raise LinkDown(f"DAQ at {self.address} reports an impossible layout (C={c}, D={depth}, rate={rate})")
        regs: list[int] = []
        for a in range(0, 5 * c, MAX_REGS):
            regs += self._input(CHANNEL_TABLE + a, min(MAX_REGS, 5 * c - a))
        channels = []
        for i in range(c):
            kind, *words = regs[5 * i : 5 * i + 5]
            raw = b"".join(w.to_bytes(2, "big") for w in words).rstrip(b"\0")
            try:
                channels.append(Channel(ChannelKind(kind), raw.decode("ascii")))
            except (ValueError, UnicodeDecodeError):
                channels.append(Channel(ChannelKind.OTHER, raw.decode("latin-1")))
        capabilities = 0
        if version >= 2:
            self._override, capabilities = self._input(IR_OVERRIDE, 2)  # 6 override applied, 7 capabilities
            capabilities &= 0xFF
        self._channels, self._ring_depth = c, depth
        self._layout = (version, c, rate, depth)
        self._v2 = version >= 2
        self._context_regs = None
        return Descriptor(rate, tuple(channels), version, capabilities)

    def _read_status(self) -> Status:
        coils = self._bits(self._call(lambda c, **kw: c.read_coils(0, count=2, **kw)), 2, "coils")
        n_inputs = 2 if self._v2 else 1  # discrete input 1 (watchdog tripped) is read from version 2 on
        inputs = self._bits(self._call(lambda c, **kw: c.read_discrete_inputs(0, count=n_inputs, **kw)), n_inputs,
                            "inputs")
        active = inputs[0]
        regs = self._call(lambda c, **kw: c.read_holding_registers(HR_HEARTBEAT, count=1, **kw)).registers
        if len(regs) != 1:
            raise LinkDown(f"DAQ at {self.address} answered {len(regs)} registers to a read of 1 at {HR_HEARTBEAT}")
        hb = regs[0]
        outputs = (OUT_FEED_HOLD if active else 0) | (OUT_ALARM_LAMP if coils[1] else 0)
        if self._v2:
            return Status(outputs, FLAG_WATCHDOG if inputs[1] else 0, hb, self._override)
        # feed hold active although not commanded: the device's watchdog asserted it
        flags = FLAG_WATCHDOG if active and not coils[0] else 0
        return Status(outputs, flags, hb)

    def _read(self) -> list:
        wait = self._next_poll - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        self._next_poll = max(self._next_poll + self.poll_s, time.monotonic())
        out: list = []
        if self._answered is not None:
            out.append(self._answered)
            self._answered = None
        if self._want_descriptor:
            self._want_descriptor = False
            out.append(self._read_descriptor())
        # The status poll goes before the ring: samples read from the ring must be handed
        # over, and a request failing after them would throw them away (and count them lost).
        if time.monotonic() >= self._next_status:  # outputs change rarely: poll them at 10 Hz
            self._next_status = time.monotonic() + STATUS_PERIOD_S
            out.append(self._read_status())
        out.extend(self._read_ring(out))
        return out

    def _head_v2(self, out: list) -> int | None:
        """Version 2: registers 0-15 in one read; the head, or None if the layout changed."""
        regs = self._input(0, V2_HEAD_REGS)
        if tuple(regs[0:4]) != self._layout:  # restarted with another layout: read its descriptor again
            self._want_descriptor = True
            return None
        override = regs[6]
        if override != self._override:
            self._override = override
            # the new override now, not at the next 10 Hz status poll (based on the newest status)
            st = next((x for x in reversed(out) if isinstance(x, Status)), self.last_status)
            if st is not None:
                out.append(Status(st.outputs, st.flags, st.last_heartbeat, override))
        ctx = tuple(regs[8:16])
        if ctx != self._context_regs:
            self._context_regs = ctx
            p_hi, p_lo, t_hi, t_lo, operation, flags, i_hi, i_lo = ctx
            out.append(Context((i_hi << 16) | i_lo, (p_hi << 16) | p_lo, (t_hi << 16) | t_lo, operation, flags & 0xFF))
        return (regs[4] << 16) | regs[5]

    def _read_ring(self, out: list) -> list[Samples]:
        c, depth = self._channels, self._ring_depth
        if self._v2:
            head = self._head_v2(out)
            if head is None:
                return []
        else:
            head = self._head()
        if self._next is None:
            self._next = head
            return []
        behind = (head - self._next) % INDEX_MOD
        if behind >= INDEX_MOD // 2:  # head went backwards: the device restarted
            self._next = head
            if self._watchdog_ms is not None:
                # with the link up (a gateway answered for it): no reconnect writes the period it forgot
                self._send_watchdog(self._watchdog_ms)
            return []
        just_connected, self._just_connected = self._just_connected, False
        if behind > depth:
            self._stats["reconnect_gaps" if just_connected else "overruns"] += 1
            # Not at the oldest sample the ring holds: the device overwrites it while it is being read,
            # and a reader that cannot keep up would start there again and again and hand over nothing.
            keep = depth - min(depth // 2, int(self._layout[2] * OVERRUN_MARGIN_S))
            self._next = (head - keep) % INDEX_MOD
            behind = keep
        if behind == 0:
            return []
        per_chunk = max(1, MAX_REGS // c)
        parts = []
        k = self._next
        remaining = behind
        sliced_at = time.monotonic() + READ_SLICE_S
        while remaining:
            slot = k % depth
            # split where the ring wraps, and where the index wraps: sample k is at slot k mod D, so with a depth
            # that does not divide 2**32 the slot of index 0 does not follow the slot of index 2**32 - 1
            n = min(per_chunk, remaining, depth - slot, INDEX_MOD - k)
            regs = self._input(RING_BASE + slot * c, n * c)
            parts.append(np.asarray(regs, dtype=np.uint16))
            k = (k + n) % INDEX_MOD
            remaining -= n
            if remaining and time.monotonic() >= sliced_at:
                self._stats["sliced_reads"] += 1
                self._next_poll = time.monotonic()  # the rest at once, in the next poll
                break
        head_after = self._head()
        first = self._next
        self._next = k
        counts = np.concatenate(parts).view(np.int16).reshape(behind - remaining, c)
        # samples older than head_after - D may have been overwritten while we read
        diff = (head_after - depth - first) % INDEX_MOD
        overwritten = min(len(counts), diff) if diff < INDEX_MOD // 2 else 0
        if overwritten:
            self._stats["overwritten_during_read"] += overwritten
            counts = counts[overwritten:]
            first = (first + overwritten) % INDEX_MOD
        if not len(counts):
            return []
        return [Samples(first, counts)]

    # -- outputs --------------------------------------------------------------

    def _checked(self, what: str, rr) -> None:
        """A write the DAQ answered with an exception response did not happen: say so."""
        if rr is None or rr.isError():
            raise CommandRefused(f"DAQ at {self.address} refused the {what} write: {rr}")

    def _send_outputs(self, bits: int) -> None:
        rr = self._client.write_coils(0, [bool(bits & OUT_FEED_HOLD), bool(bits & OUT_ALARM_LAMP)], device_id=self.unit)
        self._checked("outputs", rr)

    def _send_heartbeat(self, counter: int) -> None:
        self._checked("heartbeat", self._client.write_register(HR_HEARTBEAT, counter, device_id=self.unit))

    def _send_watchdog(self, ms: int) -> None:
        self._call(lambda cl, **kw: cl.write_register(HR_WATCHDOG, ms, **kw))

    def _send_request_descriptor(self) -> None:
        self._want_descriptor = True

    def _send_feed_override(self, tenths: int) -> None:
        self._checked("feed override", self._client.write_register(HR_FEED_OVERRIDE, tenths, device_id=self.unit))

    def set_watchdog_ms(self, ms: int) -> None:
        """Holding register 101; remembered and written again after every reconnect and restart (`_read_ring`)."""
        self._watchdog_ms = int(ms)
        self._send(
            "watchdog",
            lambda: self._checked("watchdog", self._client.write_register(HR_WATCHDOG, int(ms), device_id=self.unit)),
        )


class ModbusTcpDriver(ModbusDriver):
    transport = "modbus-tcp"

    def __init__(self, host: str, tcp_port: int = 502, **kwargs) -> None:
        super().__init__(**kwargs)
        if not host:
            raise ValueError("modbus-tcp transport needs a host")
        self.host = host
        self.tcp_port = int(tcp_port)

    @classmethod
    def from_options(cls, host: str = "", tcp_port: int = 502, unit: int = 1, poll_ms: int = 20,
                     timeout_ms: int = DEFAULT_TIMEOUT_MS, **_ignored):
        return cls(host, tcp_port, unit=unit, poll_ms=poll_ms, timeout_ms=timeout_ms)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.tcp_port}"

    def _silent(self, how: str) -> str:
        return (f"connected to {self.address} but the DAQ unit {self.unit} did not answer {how}: check unit id; "
                f"behind a gateway, its serial side: baud rate, wiring")

    def _make_client(self):
        from pymodbus.client import ModbusTcpClient

        return ModbusTcpClient(self.host, port=self.tcp_port, timeout=self.timeout_s, retries=0)


class ModbusRtuDriver(ModbusDriver):
    """RTU over a serial port.  pymodbus' sync serial client manages ~430 requests/s,
    enough for 8 channels at 1 kHz with poll_ms >= 20 but little more."""

    transport = "modbus-rtu"

    def __init__(self, port: str, baudrate: int = 921600, **kwargs) -> None:
        super().__init__(**kwargs)
        if not port:
            raise ValueError("modbus-rtu transport needs a port")
        self.port = port
        self.baudrate = int(baudrate)

    @classmethod
    def from_options(cls, port: str = "", baudrate: int = 921600, unit: int = 1, poll_ms: int = 20,
                     timeout_ms: int = DEFAULT_TIMEOUT_MS, **_ignored):
        return cls(port, baudrate, unit=unit, poll_ms=poll_ms, timeout_ms=timeout_ms)

    @property
    def address(self) -> str:
        return self.port

    def _silent(self, how: str) -> str:
        return (f"the port opened but the DAQ at {self.address} unit {self.unit} did not answer {how}: "
                f"check unit id, baud rate, wiring")

    def _make_client(self):
        from pymodbus import FramerType
        from pymodbus.client import ModbusSerialClient

        return ModbusSerialClient(
            self.port, framer=FramerType.RTU, baudrate=self.baudrate, timeout=self.timeout_s, retries=0
        )
