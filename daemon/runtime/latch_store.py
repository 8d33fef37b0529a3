"""The latched interlock on disk, so that a power cut or a crash of the daemon does not release the feed.

Why a file and a writer thread:

- **Atomic.** A state is written to a temporary file in the same directory,
  fsynced, renamed over `latch.json` and the directory fsynced: after a power
  cut the file is either the old state or the new one, never half of each.
- **Off the tripping thread.** `save()` only hands the newest state to the
  writer thread and returns; the trip that called it never waits for a disk
  (an SD card can take a second to fsync). Only the newest state is written:
  a trip followed by a reset before the disk answered writes the reset.
  What a power cut can lose is the state of its last moments: a trip within
  one fsync of the cut (milliseconds, up to about a second on a slow SD
  card) may come back unlatched. If the DAQ kept its output through the cut,
  the daemon still finds the hold at start (`held_by_device`) and leaves it.
- **Never a crash.** A read-only or full disk is reported through `on_error`
  (the runner turns it into the fault `latch_store`) and logged; the
  interlock itself goes on.
- **Cleared by a reset.** A reset removes the file (and fsyncs the
  directory), so a latch is asserted again at start until an explicit reset.

The directory is `daemon/state_dir.py`'s (`state_dir`, `claim_state_dir`). The demo (no
`--config`) persists nothing: it builds no store.
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any, Callable

import structlog

from millsense.daemon.guarded import call_quietly
from millsense.daemon.state_dir import ensure_dir
from millsense.drivers.base import name_os_thread

log = structlog.get_logger("millsense.latch")

LATCH_FILE = "latch.json"


class LatchStore:
    """The latch file of one machine, written by its own thread. Thread-safe."""

    def __init__(self, directory: Path, on_error: Callable[[str], Any] | None = None,
                 on_ok: Callable[[], Any] | None = None):
        self.directory = Path(directory)
        self.path = self.directory / LATCH_FILE
        self.on_error = on_error
        self.on_ok = on_ok
        self._cond = threading.Condition()
        self._pending: dict[str, Any] | None = None
        self._has_pending = False
        self._busy = False
        self._closing = False
        self._thread: threading.Thread | None = None
        self.writes = 0
        self.write_errors = 0

    # -- reading, at start ------------------------------------------------------
    def load(self) -> dict[str, Any] | None:
        """The persisted latch, or None when none is latched.

        A file that cannot be read or parsed is reported as latched: the feed
        held for a reason we can no longer read is the safe side.
        """
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        except OSError as exc:
            return {"latched": True, "reason": f"latch file unreadable: {exc}", "since": None, "trips": 0}
        try:
            state = json.loads(text)
            if not isinstance(state, dict):
                raise ValueError("not an object")
        except ValueError as exc:
            return {"latched": True, "reason": f"latch file damaged ({exc}): {self.path}", "since": None, "trips": 0}
        if not state.get("latched"):
            return None
        since = state.get("since")
        return {
            "latched": True,
            "reason": str(state.get("reason") or "unknown"),
            "since": float(since) if isinstance(since, (int, float)) else None,
            "trips": int(state.get("trips") or 0) if isinstance(state.get("trips"), int) else 0,
        }

    # -- writing ------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="millsense-latch", daemon=True)
            self._thread.start()

    def save(self, record: dict[str, Any]) -> None:
        """Hand the newest latch record to the writer; returns at once."""
        with self._cond:
            self._pending = dict(record)
            self._has_pending = True
            self._cond.notify_all()

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait (bounded) until everything saved so far is on disk (or failed). True if done."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._has_pending and not self._busy, timeout_s)

    def close(self, timeout_s: float = 1.0) -> None:
        self.flush(timeout_s)
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def _run(self) -> None:
        name_os_thread("ms-latch")
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._has_pending or self._closing)
                if not self._has_pending:
                    return
                record, self._pending, self._has_pending = self._pending, None, False
                self._busy = True
            try:
                self._write(record)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _write(self, record: dict[str, Any] | None) -> None:
        try:
            ensure_dir(self.directory)
            if record and record.get("latched"):
                self._replace(json.dumps(record, separators=(",", ":")) + "\n")
            else:
                try:
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
                self._sync_dir()
        except OSError as exc:  # read-only or full disk: a fault, never a crash
            self.write_errors += 1
            log.error("latch_store.write_failed", path=str(self.path), error=str(exc))
            self._call(self.on_error, f"cannot persist the interlock latch to {self.path}: {exc}")
            return
        self.writes += 1
        self._call(self.on_ok)

    def _replace(self, text: str) -> None:
        tmp = self.path.with_name(f".{LATCH_FILE}.{os.getpid()}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
        try:
            try:
                os.write(fd, text.encode("utf-8"))
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
        except OSError:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        self._sync_dir()

    def _sync_dir(self) -> None:
        # the rename (or unlink) is durable only once the directory entry is on disk
        fd = os.open(self.directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    @staticmethod
    def _call(fn: Callable[..., Any] | None, *args: Any) -> None:
        call_quietly(fn, "latch_store.callback_failed", *args)
