"""The historian's loop: Zenoh's publications in, rows out through the writer, at least one flush a second; a
status line every `STATUS_EVERY_S`; SIGTERM flushes (to PostgreSQL, or to the spool) and ends (docs/historian.md).

Zenoh's callbacks only keep what came (`Inbox`: the key, the bytes, the time, appended to a list under a lock held
for the append); one thread, this loop's, takes the list whole every `TAKE_S`, parses it, turns the payloads into
rows, keeps the per-second aggregates and the change detectors, and writes: none of that state is shared. Issue
43's profile: the callbacks and the loop take turns under one GIL, so every microsecond a payload costs in Python
is one the plant's rate pays; the callback's share is now an append.
"""

from __future__ import annotations

import json
import threading
import time
from collections import Counter
from typing import Any

from millsense.daemon.historian import rows as rowmod
from millsense.daemon.historian.writer import Writer

KINDS = ("alarm", "process", "status", "estimate", "limits/change")
FLUSH_S = 1.0
TAKE_S = 0.1           # the loop takes what came this often between flushes (its parsing spread over the second)
STATUS_EVERY_S = 10.0
MAX_PAYLOAD_BYTES = 256 * 1024
MAX_QUEUED = 500_000   # payloads waiting for the loop: past it they are counted and dropped (memory stays bounded)
MAX_KEYS = 100_000     # key → machine kept for this many keys (a publisher of ever new keys cannot grow it unbounded)

# NaN and ±Infinity are no JSON: null (parse_constant). One decoder, made once: `json.loads(data, parse_constant=…)`
# makes a new decoder and scanner for every call, a third of what a payload's parsing cost (issue 43's profile).
_DECODER = json.JSONDecoder(parse_constant=lambda _: None)
_SCAN = _DECODER.scan_once


def machine_of(key: str) -> str | None:
    parts = key.split("/")
    return parts[1] if len(parts) in (3, 4) and parts[0] == "millsense" else None


def parse(data: bytes) -> Any:
    """A payload's JSON (UTF-8) as `json.loads` reads it, NaN and ±Infinity as None; ValueError when it is none.
    The scanner straight on the text first (a payload is one value with no whitespace around it, as the daemon
    writes it); anything else through the decoder, which takes the whitespace or says what is wrong."""
    text = data.decode()   # UnicodeDecodeError is a ValueError
    try:
        value, end = _SCAN(text, 0)
    except StopIteration:
        end = -1
    return value if end == len(text) else _DECODER.decode(text)


class Inbox:
    """What Zenoh's callbacks bring, in arrival order: (kind, key, bytes, received_at). `take()` hands the loop
    everything so far and starts a new list."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[tuple[str, str, bytes, float]] = []
        self.received: Counter = Counter()   # payloads taken into rows, by kind (the loop counts them)
        self.refused = 0                      # no machine in the key, too large, no JSON object
        self.overflow = 0                     # past MAX_QUEUED waiting

    def callback(self, kind: str) -> Any:
        items, lock = self, self._lock

        def on_sample(sample: Any) -> None:
            received_at = time.time()
            data = sample.payload.to_bytes()
            key = str(sample.key_expr)
            with lock:
                if len(data) > MAX_PAYLOAD_BYTES:
                    items.refused += 1
                elif len(items._items) >= MAX_QUEUED:
                    items.overflow += 1
                else:
                    items._items.append((kind, key, data, received_at))

        return on_sample

    def take(self) -> list[tuple[str, str, bytes, float]]:
        with self._lock:
            out, self._items = self._items, []
        return out

    def waiting(self) -> int:
        return len(self._items)

    def refuse(self, n: int) -> None:
        with self._lock:
            self.refused += n


class Rows:
    """Payloads → the writer's rows: the per-kind row makers and the state some of them keep."""

    def __init__(self, writer: Writer, revolutions_for: set[str]) -> None:
        self.writer, self.revolutions_for = writer, revolutions_for
        self.status_changes = rowmod.StatusChanges()
        self.limit_changes = rowmod.LimitChanges()
        self.load = rowmod.LoadSeconds()
        self.malformed = 0
        self._machines: dict[str, str | None] = {}   # key → machine (machine_of, once a key)

    def take_batch(self, inbox: Inbox, items: list[tuple[str, str, bytes, float]]) -> None:
        """What the callbacks kept, in order: each parsed and made rows of (`take`); a payload with no machine in
        its key or no JSON object is counted refused. Estimates (all but a few of the plant's payloads) go
        straight to the aggregate and, for `revolutions_for`'s machines, their row: no dispatch on the way."""
        machines, load, writer = self._machines, self.load, self.writer
        revolutions_for, received = self.revolutions_for, inbox.received
        load_rows, revolution_rows = writer.rows("load_1s"), writer.rows("revolutions")
        refused = 0
        counted: Counter = Counter()
        for kind, key, data, received_at in items:
            machine = machines.get(key, False)
            if machine is False:
                if len(machines) >= MAX_KEYS:
                    machines.clear()
                machine = machines[key] = machine_of(key)
            if machine is None:
                refused += 1
                continue
            try:
                payload = parse(data)
            except (ValueError, RecursionError):   # not JSON; nested deeper than the parser goes
                payload = None
            if type(payload) is not dict:
                refused += 1
                continue
            counted[kind] += 1
            if kind == "estimate":
                closed = load.add(machine, payload, received_at)
                if closed:
                    load_rows.extend(closed)
                if machine in revolutions_for:
                    row = rowmod.revolution_row(machine, payload, received_at)
                    if row is None:
                        self.malformed += 1
                    else:
                        revolution_rows.append(row)
            else:
                self.take(kind, machine, payload, received_at)
        received.update(counted)
        if refused:
            inbox.refuse(refused)

    def take(self, kind: str, machine: str, payload: dict[str, Any], received_at: float) -> None:
        add = self.writer.add
        if kind == "estimate":
            for row in self.load.add(machine, payload, received_at):
                add("load_1s", row)
            if machine in self.revolutions_for:
                row = rowmod.revolution_row(machine, payload, received_at)
                self._add("revolutions", row)
        elif kind == "alarm":
            self._add("alarms", rowmod.alarm_row(machine, payload, received_at))
        elif kind == "process":
            self._add("processes", rowmod.process_row(machine, payload, received_at))
            row = self.limit_changes.row(machine, payload, received_at)
            if row is not None:
                add("limit_changes", row)
        elif kind == "limits/change":
            self._add("limit_changes", self.limit_changes.published(machine, payload, received_at))
        elif kind == "status":
            row = self.status_changes.row(machine, payload, received_at)
            if row is not None:
                add("status_changes", row)

    def _add(self, table: str, row: list[Any] | None) -> None:
        if row is None:
            self.malformed += 1
        else:
            self.writer.add(table, row)

    def close_idle(self, now: float) -> None:
        for row in self.load.close_idle(now):
            self.writer.add("load_1s", row)

    def close_all(self) -> None:   # the historian stops: every open second is all it will see of it
        for row in self.load.close_all():
            self.writer.add("load_1s", row)


def serve(session: Any, machines: str, writer: Writer, rows: Rows, stop: threading.Event, log: Any,
          on_status: Any = None) -> None:
    inbox = Inbox()
    subs = [session.declare_subscriber(f"millsense/{machines}/{kind}", inbox.callback(kind)) for kind in KINDS]
    log.info("historian.subscribed", keys=[f"millsense/{machines}/{k}" for k in KINDS])
    next_flush = time.monotonic() + FLUSH_S
    next_status = time.monotonic() + STATUS_EVERY_S
    try:
        while not stop.is_set():
            _drain(inbox, rows, until=next_flush, stop=stop)
            # the next flush a second after this one's start, not its end: a slow flush's time is not added to the
            # wait of every payload that comes meanwhile (at a plant's rate it was most of the p99)
            next_flush = time.monotonic() + FLUSH_S
            rows.close_idle(time.time())
            writer.flush()
            now = time.monotonic()
            if now >= next_status:
                next_status = now + STATUS_EVERY_S
                _status(log, inbox, rows, writer, on_status)
    finally:
        for sub in subs:
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass
        _drain_all(inbox, rows)
        rows.close_all()
        writer.close()
        _status(log, inbox, rows, writer, on_status, event="historian.stopped")


def _drain(inbox: Inbox, rows: Rows, until: float, stop: threading.Event | None) -> None:
    """Take what comes, every `TAKE_S`, until the flush is due: then return, however much is still coming (a
    steady flood must not hold back the flush; what comes meanwhile waits for the next cycle)."""
    waiter = stop if stop is not None else threading.Event()
    while True:
        items = inbox.take()
        if items:
            rows.take_batch(inbox, items)
        timeout = until - time.monotonic()
        if timeout <= 0 or waiter.is_set():
            return
        waiter.wait(min(timeout, TAKE_S))


def _drain_all(inbox: Inbox, rows: Rows) -> None:
    """Everything kept now (the historian stops)."""
    rows.take_batch(inbox, inbox.take())


def _status(log: Any, inbox: Inbox, rows: Rows, writer: Writer, on_status: Any,
            event: str = "historian.status") -> None:
    state = writer.status()
    fields = dict(state, received=dict(inbox.received), refused=inbox.refused, overflow=inbox.overflow,
                  malformed=rows.malformed, waiting=inbox.waiting())
    (log.warning if state["db"] == "down" or state["spooled_rows"] else log.info)(event, **fields)
    if on_status is not None:
        on_status(state)
