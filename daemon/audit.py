"""The audit trail of commands that change the machine: who asked what, granted or refused, when.

Every command (`cmd/*` over Zenoh, the local reset at the machine, `test-trip`)
is one record, whatever the outcome: a JSON line appended to `audit.log` in the
daemon's state directory (when it has one) and one `audit` log event. Records
are small and rare for granted commands; refusals under a flood are counted
and written at most once per `REFUSAL_EVERY_S` with the count, so a flood can
neither fill the disk nor bury the real lines in the journal.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path
from typing import Any

import structlog

from millsense.daemon.throttle import Throttle

REFUSAL_EVERY_S = 10.0
MAX_BYTES = 4 * 1024 * 1024  # audit.log is renamed to audit.log.1 past this (one generation kept)

log = structlog.get_logger("millsense.audit")


class AuditLog:
    """Thread-safe. `path` None: log events only (the demo, tests without a state directory)."""

    def __init__(self, path: str | os.PathLike[str] | None, machine: str = "", clock: Any = time.time,
                 mono: Any = time.monotonic):
        self.path = Path(path) if path is not None else None
        self.machine = machine
        self._clock, self._mono = clock, mono
        self._lock = threading.Lock()
        self._refused = Throttle(REFUSAL_EVERY_S, mono)
        self.records = 0
        self.refusals = 0

    def record(self, command: str, requester: str, granted: bool, reason: str | None = None,
               result: dict[str, Any] | None = None) -> None:
        """One command's outcome. Refusals are rate-limited (counted, written once per REFUSAL_EVERY_S)."""
        entry: dict[str, Any] = {"t": round(self._clock(), 3), "machine": self.machine, "command": command,
                                 "requester": requester or "unknown", "granted": bool(granted)}
        if reason:
            entry["reason"] = reason
        if result is not None:
            entry["result"] = result
        with self._lock:
            if not granted:
                self.refusals += 1
                due = self._refused.note(entry)
                if due is None:
                    return
                count, entry = due
                entry = dict(entry, refused_since_last=count)
            self._write(entry)

    def flush(self) -> None:
        """Write the refusals counted since the last written one (at stop)."""
        with self._lock:
            due = self._refused.pending()
            if due is not None:
                count, entry = due
                self._write(dict(entry, refused_since_last=count))

    def _write(self, entry: dict[str, Any]) -> None:
        self.records += 1
        event = "audit.granted" if entry["granted"] else "audit.refused"
        (log.info if entry["granted"] else log.warning)(event, **{k: v for k, v in entry.items() if k != "granted"})
        if self.path is None:
            return
        try:
            if self.path.exists() and self.path.stat().st_size > MAX_BYTES:
                os.replace(self.path, self.path.with_name(self.path.name + ".1"))
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o640)
            try:
                os.write(fd, (json.dumps(entry, separators=(",", ":")) + "\n").encode())
            finally:
                os.close(fd)
        except OSError as exc:  # a full or read-only disk must not stop the daemon
            log.error("audit.write_failed", path=str(self.path), error=str(exc))
