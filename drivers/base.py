"""What every DAQ transport shares: the reader thread, reconnects, the queue, index tracking.

A transport implements a narrow connect / read / write surface (``_connect``,
``_read``, ``_disconnect`` and the ``_send_*`` outputs); this base class owns the
thread, the doubling back-off, the one log event per link state change, the bounded
queue that never blocks the reader, and the turning of 32-bit device indices into a
monotonic 64-bit ``seq`` with counted gaps.

Two ways to consume (issue 13): ``get()`` hands over one event at a time and wakes
its caller for each; a batching consumer (the daemon's estimator thread) sets
``sample_hook`` — called on the reader thread for every sample block before it is
queued (the daemon's per-frame crash check), saying whether the consumer must
wake now — waits on ``wake`` and takes everything queued with ``drain()``.
Anything but a sample block sets ``wake``, except a STATUS in which only the
echo of the last heartbeat changed.
"""

from __future__ import annotations

import collections
import ctypes
import sys
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
import structlog

from millsense.drivers.protocol import (
    CMD_HEARTBEAT,
    CMD_SEND_DESCRIPTOR,
    CMD_SET_FEED_OVERRIDE,
    CMD_SET_OUTPUTS,
    FEED_OVERRIDE_MAX,
    INDEX_MOD,
    Command,
    Context,
    Descriptor,
    Samples,
    Status,
    StreamDecoder,
    encode_command,
)

log = structlog.get_logger("millsense.drivers")


@dataclass(frozen=True, eq=False)
class SampleBlock:
    seq: int  # unwrapped 64-bit index of the first sample (monotonic per driver lifetime)
    index: int  # the device's 32-bit index of the first sample
    counts: np.ndarray  # (n, C) int16 raw counts, channel order of the current descriptor
    lost_before: int  # samples known lost right before this block
    discontinuity: bool  # device restart / index went backwards / descriptor changed
    checked: bool = False  # the sample_hook looked at it on the reader thread (the crash check ran)
    received_mono: float = 0.0  # time.monotonic() when the reader decoded it (0: not stamped)
    after_link_up: bool = False  # the first block since the link came (back) up: the gap before it is the outage's


@dataclass(frozen=True)
class LinkEvent:
    up: bool
    reason: str


Event = SampleBlock | Descriptor | Status | Context | LinkEvent


class LinkDown(Exception):
    """Raised by a transport when its link is gone; the message is the reason."""


class CommandRefused(Exception):
    """Raised by a transport when the DAQ answered a command with a refusal (a Modbus
    exception response): the link is fine, the command did not take effect."""


class IndexTracker:
    """Unwraps the device's 32-bit sample index into a 64-bit ``seq`` and finds gaps.

    A forward jump of less than 2**31 is a gap of lost samples; anything else is
    the index going backwards (a device restart): a discontinuity, with no lost
    count invented for it.
    """

    def __init__(self) -> None:
        self.next_index: int | None = None  # device index expected next
        self.next_seq = 0
        self._force_discontinuity = False
        self.went_back = False  # the last `update`'s index went backwards: the device restarted

    def mark_discontinuity(self) -> None:
        self._force_discontinuity = True

    def update(self, index: int, n: int) -> tuple[int, int, bool]:
        """Account for ``n`` samples starting at device ``index``: (seq, lost_before, discontinuity)."""
        index %= INDEX_MOD
        discontinuity = self._force_discontinuity
        self._force_discontinuity = False
        self.went_back = False
        if self.next_index is None:
            seq, lost = index, 0
        else:
            gap = (index - self.next_index) % INDEX_MOD
            if gap < INDEX_MOD // 2:
                seq, lost = self.next_seq + gap, gap
            else:
                seq, lost, discontinuity = self.next_seq, 0, True
                self.went_back = True
        self.next_index = (index + n) % INDEX_MOD
        self.next_seq = seq + n
        return seq, lost, discontinuity


class _BoundedQueue:
    """Hand-off from the reader thread: never blocks the producer.

    Sample blocks are refused when ``maxsize`` items wait; other events (rare:
    link changes, descriptors, status changes) get a small reserve above that.
    """

    RESERVE = 64

    def __init__(self, maxsize: int) -> None:
        self.maxsize = maxsize
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()

    def offer(self, item, is_sample: bool) -> bool:
        with self._cond:
            limit = self.maxsize if is_sample else self.maxsize + self.RESERVE
            if len(self._items) >= limit:
                return False
            self._items.append(item)
            self._cond.notify()
            return True

    def get(self, timeout: float | None):
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def drain(self) -> list:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def __len__(self) -> int:
        return len(self._items)


class Driver:
    """Base of every transport; see docs/architecture.md "drivers.base".

    Subclasses implement ``_connect()`` (raise OSError/LinkDown on failure),
    ``_read()`` -> list of Samples/Descriptor/Status/Context (return within ~0.2 s, raise
    LinkDown/OSError when the link is gone), ``_disconnect()``, and the outputs
    ``_send_outputs(bits)``, ``_send_heartbeat(counter)``, ``_send_request_descriptor()``
    and (protocol version 2) ``_send_feed_override(tenths)``.
    """

    transport = "?"

    def __init__(
        self,
        *,
        queue_size: int = 1000,
        backoff_initial_s: float = 0.1,
        backoff_max_s: float = 5.0,
    ) -> None:
        self.link_up = False
        self.descriptor: Descriptor | None = None
        self.last_status: Status | None = None
        self.last_context: Context | None = None
        self._said_no_override = False
        self._queue = _BoundedQueue(queue_size)
        self._backoff_initial_s = backoff_initial_s
        self._backoff_max_s = backoff_max_s
        self._tracker = IndexTracker()
        self._closing = threading.Event()
        self._closing_why = ""  # who closed it, said in the log (`close`)
        self._connected = threading.Event()
        self.last_connect_error: str | None = None   # why the last try to connect failed (for `run`'s message)
        self._thread: threading.Thread | None = None
        self._io_lock = threading.Lock()
        self._heartbeat_counter = 0
        self._pending_lost = 0
        self._link_state: bool | None = None
        self._after_link_up = False  # the next block queued is the first since the link came up
        # A device that restarted under the stream may come back with other channels of the same width; until a
        # DESCRIPTOR confirms them its samples are held back (counted lost) and it is asked for one (`_unconfirmed`)
        self._descriptor_fresh = False   # a DESCRIPTOR came after the last SAMPLES
        self._awaiting_descriptor: float | None = None   # monotonic time of the last request while unconfirmed
        self._pending_disc = False
        self._stats = collections.Counter()
        # set by a batching consumer: (seq, counts, lost_before, discontinuity) -> (checked, wake now)
        self.sample_hook = None
        self.wake = threading.Event()

    # -- public ---------------------------------------------------------------

    @property
    def address(self) -> str:
        return "?"

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name=f"daq-{self.transport}", daemon=True)
        self._thread.start()

    def close(self, why: str = "") -> None:
        """Stop the reader and the link. `why` is who asked, for the log (issue 39: `record` is not the daemon):
        `daq.link_down`'s detail reads "the driver is closing, as asked (WHY)"."""
        self._closing_why = why
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._io_lock:
            self._safe_disconnect()

    def __enter__(self) -> Driver:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def get(self, timeout: float | None = None) -> Event | None:
        return self._queue.get(timeout)

    def drain(self) -> list[Event]:
        """Everything queued, oldest first, without waiting (a batching consumer waits on ``wake``)."""
        return self._queue.drain()

    @property
    def queued(self) -> int:
        """Events waiting in the receive queue (cheap: the consumer asks once per block)."""
        return len(self._queue)

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    def set_outputs(self, feed_hold: bool, alarm_lamp: bool = False) -> bool:
        """Write the outputs; False if the command could not be sent or the DAQ refused it."""
        bits = (1 if feed_hold else 0) | (2 if alarm_lamp else 0)
        return self._send("outputs", self._send_outputs, bits)

    def heartbeat(self) -> bool:
        """Send a changing heartbeat counter; False if it could not be sent or was refused."""
        self._heartbeat_counter = (self._heartbeat_counter + 1) & 0xFFFF
        return self._send("heartbeat", self._send_heartbeat, self._heartbeat_counter)

    def set_watchdog_ms(self, ms: int) -> None:
        """Stream transports: a device setting, nothing to send."""

    def request_descriptor(self) -> bool:
        return self._send("descriptor request", self._send_request_descriptor)

    def set_feed_override(self, percent_tenths: int) -> bool:
        """Command the CNC's feed override (0.1 % steps, 0..2000; 1000 = the programmed feed).

        False when not sent or refused, and always on a DAQ whose descriptor does not
        announce a feed-override output (protocol version 1): that is logged once.
        A value outside 0..2000 is a caller's mistake: ValueError.
        """
        tenths = int(percent_tenths)
        if not 0 <= tenths <= FEED_OVERRIDE_MAX:
            raise ValueError(f"feed override {tenths} outside 0..{FEED_OVERRIDE_MAX} (0.1 % steps)")
        d = self.descriptor
        if d is None:  # not connected yet: the DAQ's abilities are unknown
            self._stats["commands_not_sent"] += 1
            return False
        if not d.has_feed_override:
            self._stats["commands_not_sent"] += 1
            if not self._said_no_override:
                self._said_no_override = True
                log.warning(
                    "daq.no_feed_override",
                    transport=self.transport,
                    address=self.address,
                    protocol_version=d.protocol_version,
                    capabilities=d.capabilities,
                )
            return False
        return self._send("feed override", self._send_feed_override, tenths)

    def stats(self) -> dict[str, int]:
        out = dict(self._stats)
        out["queue_len"] = self.queued
        out["link_up"] = int(self.link_up)
        return out

    # -- for subclasses -------------------------------------------------------

    def _connect(self) -> None:
        raise NotImplementedError

    def _disconnect(self) -> None:
        raise NotImplementedError

    def _read(self) -> list:
        raise NotImplementedError

    def _send_outputs(self, bits: int) -> None:
        raise NotImplementedError

    def _send_heartbeat(self, counter: int) -> None:
        raise NotImplementedError

    def _send_request_descriptor(self) -> None:
        raise NotImplementedError

    def _send_feed_override(self, tenths: int) -> None:
        raise NotImplementedError

    def _after_connect(self) -> None:
        """Hook run on the reader thread once connected (e.g. ask for the descriptor)."""

    # -- the reader thread ----------------------------------------------------

    def _send(self, what: str, fn, *args) -> bool:
        """Outputs from any thread; True if sent (and, where the transport answers, accepted).

        A failure is counted and returned, never raised (the reader notices a lost link).
        """
        if not self.link_up:
            self._stats["commands_not_sent"] += 1
            return False
        try:
            with self._io_lock:
                fn(*args)
            self._stats["commands_sent"] += 1
            return True
        except Exception as exc:  # noqa: BLE001 - a write must never kill the caller
            key = "commands_refused" if isinstance(exc, CommandRefused) else "commands_failed"
            self._stats[key] += 1
            log.debug("daq command failed", transport=self.transport, command=what, error=str(exc))
            return False

    def _run(self) -> None:
        name_os_thread(f"ms-daq-{self.transport}")
        backoff = self._backoff_initial_s
        while not self._closing.is_set():
            try:
                with self._io_lock:
                    self._connect()
            except Exception as exc:  # noqa: BLE001 - any failure to connect is "down, retry"
                self.last_connect_error = _reason(exc)
                self._set_link(False, f"connect failed: {self.last_connect_error}")
                self._stats["connect_failures"] += 1
                if self._closing.wait(backoff):
                    break
                backoff = min(backoff * 2, self._backoff_max_s)
                continue
            backoff = self._backoff_initial_s
            # no discontinuity here: if the device kept counting, the index gap is
            # the time we were away; if it restarted, the index goes backwards
            self._set_link(True, "connected")
            try:
                self._after_connect()
                while not self._closing.is_set():
                    for item in self._read():
                        self._handle(item)
                reason = "closed"
            except Exception as exc:  # noqa: BLE001 - a lost link is an event, not a traceback
                reason = _reason(exc)
            with self._io_lock:
                self._safe_disconnect()
            self._set_link(False, reason)
            if not self._closing.is_set() and self._closing.wait(self._backoff_initial_s):
                break

    def _safe_disconnect(self) -> None:
        try:
            self._disconnect()
        except Exception:  # noqa: BLE001 - closing a dead link may fail; it is closed either way
            pass

    def _set_link(self, up: bool, reason: str) -> None:
        self.link_up = up
        if up:
            self._connected.set()
        if self._link_state is up:
            return
        was, self._link_state = self._link_state, up
        self._after_link_up = up
        self._stats["link_changes"] += 1
        # a lost or refused link is something to act on: warning, like the daemon's own "unreachable";
        # a link ended because the driver is closing (the daemon or `record` stopping) was asked for: info
        asked = not up and self._closing.is_set()
        why = f" ({self._closing_why})" if self._closing_why else ""
        extra = {"detail": f"the driver is closing, as asked{why}"} if asked else {}
        (log.info if up or asked else log.warning)(
            "daq.link_up" if up else "daq.link_down",
            transport=self.transport,
            address=self.address,
            reason=reason,
            **extra,
        )
        if up or was is not None:
            # A link that was never up was not lost: a consumer started once it came up (`run` waits
            # for the DAQ first) would otherwise see a stale "down", a fault and daq_lost/clear at once.
            self._queue.offer(LinkEvent(up, reason), is_sample=False)
        self.wake.set()

    def _handle(self, item) -> None:
        if isinstance(item, Samples):
            received = time.monotonic()
            n = len(item.counts)
            seq, lost, disc = self._tracker.update(item.first_index, n)
            self._stats["samples"] += n
            self._stats["lost_samples"] += lost
            if self._unconfirmed(received, n, lost):
                return
            disc = disc or self._pending_disc
            checked, wake = self._hook(seq, item.counts, lost, disc)  # before the queue: a full one drops it
            block = SampleBlock(seq, item.first_index, item.counts, lost + self._pending_lost, disc, checked, received,
                                self._after_link_up)
            if self._queue.offer(block, is_sample=True):
                self._pending_lost = 0
                self._after_link_up = self._pending_disc = False   # a dropped block's marks are carried, as its losses are
                self._stats["blocks"] += 1
            else:
                self._pending_lost += lost + n  # lost_before of the dropped block is carried too
                self._stats["queue_dropped_samples"] += n
            if wake:
                self.wake.set()
            return
        if isinstance(item, Descriptor):
            self._descriptor_fresh = True
            if self._awaiting_descriptor is not None:
                self._awaiting_descriptor = None
                log.info("daq.channels_confirmed", transport=self.transport, channels=list(item.names),
                         held_back=self._stats["samples_unconfirmed"])
            if item == self.descriptor:
                return
            if self.descriptor is not None:
                self._tracker.mark_discontinuity()
            self.descriptor = item
        elif isinstance(item, Status):
            prev, self.last_status = self.last_status, item
            if item == prev:
                return
            if prev is not None and replace(item, last_heartbeat=prev.last_heartbeat) == prev:
                # only the echo of our heartbeat moved (10 times a second): queued, no wake-up for it
                self._queue.offer(item, is_sample=False)
                return
        elif isinstance(item, Context):
            # the device repeats it once a second: only a change is an event
            changed = item != self.last_context
            self.last_context = item
            if not changed:
                return
        else:
            return
        self._queue.offer(item, is_sample=False)
        self.wake.set()

    def _unconfirmed(self, now: float, n: int, lost: int) -> bool:
        """Are these samples of a device that restarted under the stream, its channels not yet confirmed?
        Then they are held back: counted lost (`samples_unconfirmed`), the next block handed on after a
        discontinuity; the device is asked for its DESCRIPTOR now and once a second until it comes."""
        fresh, self._descriptor_fresh = self._descriptor_fresh, False
        if self._tracker.went_back and not fresh and self.descriptor is not None:
            if self._awaiting_descriptor is None:
                log.warning("daq.restarted_unconfirmed", transport=self.transport, address=self.address,
                            detail="the sample index went back without a DESCRIPTOR: the DAQ restarted under the "
                                   "stream; its samples are held back until its DESCRIPTOR confirms the channels")
            self._awaiting_descriptor = now - 2.0
        if self._awaiting_descriptor is None:
            return False
        if now - self._awaiting_descriptor >= 1.0:
            self._awaiting_descriptor = now
            self.request_descriptor()
        self._stats["samples_unconfirmed"] += n
        self._pending_lost += lost + n
        self._pending_disc = True
        return True

    def _hook(self, seq: int, counts, lost: int, disc: bool) -> tuple[bool, bool]:
        """The consumer's per-frame look (see the module doc); without one every block wakes it."""
        hook = self.sample_hook
        if hook is None:
            return False, True
        try:
            return hook(seq, counts, lost, disc)
        except Exception as exc:  # noqa: BLE001 - the reader must go on; the consumer checks the block itself
            self._stats["sample_hook_errors"] += 1
            log.error("daq.sample_hook_failed", transport=self.transport, error=f"{type(exc).__name__}: {exc}")
            return False, True


_PR_SET_NAME = 15


def name_os_thread(name: str) -> None:
    """Give the calling thread `name` in the OS too (`top -H`, `ps -L`, /proc/<pid>/task/*/comm):
    Python 3.11 leaves every thread called after the executable. Linux keeps 15 bytes. Best effort."""
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_NAME, ctypes.c_char_p(name.encode("ascii", "replace")[:15]), 0, 0, 0)
    except Exception:  # noqa: BLE001 - a name is a convenience; no prctl, no name
        pass


def _reason(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


class StreamDriver(Driver):
    """A transport that carries the framed byte stream (serial port, TCP socket).

    Subclasses implement ``_open()``, ``_close()``, ``_wait_readable(timeout_s)``
    (block until bytes are there, False after the timeout), ``_read_bytes()``
    (return what is there without waiting; raise LinkDown at end of stream) and
    ``_write(bytes)``.

    One wake-up per arriving frame: the reader sleeps in `_wait_readable` until
    bytes land and reads them at once. Only when they land sooner than
    ``read_interval_s`` after the last read does it wait out the rest, so that a
    DAQ sending one sample a frame wakes the reader at most 500 times a second,
    not 1000. A DAQ sending 10-sample frames (100 a second) is read as each frame
    lands: the spacing adds no delay to the sample-level crash trip there. (An
    earlier version slept out the spacing *after* each read and then waited for
    data: two wake-ups per frame, and each wake-up costs about half a
    millisecond of CPU on a VM.)
    """

    read_interval_s = 0.002
    read_block_s = 0.2  # longest wait for data before the reader loop looks up (close, stop)

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self._decoder = StreamDecoder()
        self._decoder_totals: collections.Counter = collections.Counter()
        self._last_read = 0.0

    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def _wait_readable(self, timeout_s: float) -> bool:
        raise NotImplementedError

    def _read_bytes(self) -> bytes:
        raise NotImplementedError

    def _write(self, data: bytes) -> None:
        raise NotImplementedError

    def _connect(self) -> None:
        self._open()
        self._decoder = StreamDecoder()

    def _disconnect(self) -> None:
        self._decoder_totals.update(self._decoder.stats.as_dict())
        self._decoder = StreamDecoder()
        self._close()

    def _after_connect(self) -> None:
        self.request_descriptor()

    def _read(self) -> list:
        if not self._wait_readable(self.read_block_s):
            return []
        wait = self._last_read + self.read_interval_s - time.monotonic()
        if wait > 0:  # frames closer together than the spacing: read them as one batch
            time.sleep(wait)
        data = self._read_bytes()
        self._last_read = time.monotonic()
        if not data:
            return []
        return self._decoder.feed(data)

    def _send_outputs(self, bits: int) -> None:
        self._write(encode_command(Command(CMD_SET_OUTPUTS, bits)))

    def _send_heartbeat(self, counter: int) -> None:
        self._write(encode_command(Command(CMD_HEARTBEAT, counter)))

    def _send_request_descriptor(self) -> None:
        self._write(encode_command(Command(CMD_SEND_DESCRIPTOR)))

    def _send_feed_override(self, tenths: int) -> None:
        self._write(encode_command(Command(CMD_SET_FEED_OVERRIDE, tenths)))

    def stats(self) -> dict[str, int]:
        out = super().stats()
        totals = self._decoder_totals.copy()
        totals.update(self._decoder.stats.as_dict())
        for key, value in totals.items():
            out[f"decoder_{key}"] = value
        out["decoder_buffered"] = self._decoder.buffered
        return out
