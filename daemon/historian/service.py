"""The historian's loop: Zenoh's publications in, rows out through the writer, at least one flush a second; a
status line every `STATUS_EVERY_S`; SIGTERM flushes (to PostgreSQL, or to the spool) and ends (docs/historian.md).

Zenoh's callbacks only queue what came (`Inbox.put`); one thread, this loop's, turns payloads into rows, keeps
the per-second aggregates and the change detectors, and writes: none of that state is shared.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections import Counter
from typing import Any

from millsense.daemon.historian import rows as rowmod
from millsense.daemon.historian.writer import Writer

KINDS = ("alarm", "process", "status", "estimate", "limits/change")
FLUSH_S = 1.0
STATUS_EVERY_S = 10.0
MAX_PAYLOAD_BYTES = 256 * 1024
MAX_QUEUED = 500_000   # payloads waiting for the loop: past it they are counted and dropped (memory stays bounded)


def machine_of(key: str) -> str | None:
    parts = key.split("/")
    return parts[1] if len(parts) in (3, 4) and parts[0] == "millsense" else None


class Inbox:
    def __init__(self) -> None:
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self.received: Counter = Counter()
        self.refused = 0
        self.overflow = 0

    def callback(self, kind: str) -> Any:
        def on_sample(sample: Any) -> None:
            received_at = time.time()
            name = machine_of(str(sample.key_expr))
            data = sample.payload.to_bytes()
            if name is None or len(data) > MAX_PAYLOAD_BYTES:
                self.refused += 1
                return
            try:
                payload = json.loads(data, parse_constant=lambda _: None)   # NaN is no JSON: null
            except (UnicodeDecodeError, ValueError):
                payload = None
            if not isinstance(payload, dict):
                self.refused += 1
                return
            if self.q.qsize() >= MAX_QUEUED:
                self.overflow += 1
                return
            self.received[kind] += 1
            self.q.put((kind, name, payload, received_at))

        return on_sample


class Rows:
    """Payloads → the writer's rows: the per-kind row makers and the state some of them keep."""

    def __init__(self, writer: Writer, revolutions_for: set[str]) -> None:
        self.writer, self.revolutions_for = writer, revolutions_for
        self.status_changes = rowmod.StatusChanges()
        self.limit_changes = rowmod.LimitChanges()
        self.load = rowmod.LoadSeconds()
        self.malformed = 0

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
            rows.close_idle(time.time())
            writer.flush()
            now = time.monotonic()
            next_flush = now + FLUSH_S
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
    """Take what comes until the flush is due: then return, however much is still coming (a steady flood must
    not hold back the flush; what is left waits for the next cycle)."""
    while True:
        timeout = until - time.monotonic()
        if timeout <= 0:
            return
        try:
            item = inbox.q.get(timeout=min(timeout, 0.2))
        except queue.Empty:
            if stop is not None and stop.is_set():
                return
            continue
        rows.take(*item)


def _drain_all(inbox: Inbox, rows: Rows) -> None:
    """Everything queued now (the historian stops)."""
    while True:
        try:
            item = inbox.q.get_nowait()
        except queue.Empty:
            return
        rows.take(*item)


def _status(log: Any, inbox: Inbox, rows: Rows, writer: Writer, on_status: Any,
            event: str = "historian.status") -> None:
    state = writer.status()
    fields = dict(state, received=dict(inbox.received), refused=inbox.refused, overflow=inbox.overflow,
                  malformed=rows.malformed)
    (log.warning if state["db"] == "down" or state["spooled_rows"] else log.info)(event, **fields)
    if on_status is not None:
        on_status(state)
