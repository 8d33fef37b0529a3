"""The history database of one machine: SQLite in WAL mode, written by one thread.

Why this shape:

- **Never in the way of monitoring.** `add_*` put the payload on a bounded
  queue and return; a full queue (a disk that stalls, a locked file) drops the
  row and counts it. Nothing here raises into the caller: a failure goes to
  `on_error(reason)` once per episode and `on_ok()` when writes work again,
  as `LatchStore` does for the latch (the runner turns them into a fault).
- **Batched, durable commits.** The writer commits what came in over at most
  `COMMIT_INTERVAL_S` (or `BATCH_ROWS` rows) in one transaction, with
  `synchronous = FULL`: the WAL is fsynced at each commit, so a committed
  batch survives a power cut. What a cut can lose is the batch being
  gathered and the queue: about one second of rows. Learned limits and the
  tool table end a batch at once (`save_limits` wakes the writer), so they
  are on disk within one commit of the call.
- **Bounded.** Revolutions older than `retention_days` go, processes and
  alarms after `OTHER_RETENTION_FACTOR` times that; above `max_mb` of used
  pages the oldest revolutions go first (then processes, then alarms; limits
  and tools never). Freed pages are reused, so the file stops growing at the
  cap; a file above it (a cap lowered) is shrunk by incremental vacuum.
- **A damaged file is moved aside.** At start a quick check runs; a file
  that fails it, or is not a database, is renamed `<name>.corrupt-<UTC>`
  (with its -wal and -shm) and a new one started; the log names it.
"""

from __future__ import annotations

import os
import queue
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any, Callable

import structlog

from millsense.daemon.history import bounds, records
from millsense.daemon.history.schema import SCHEMA_VERSION, NewerSchemaError, check_version, migrate, version_of
from millsense.daemon.runtime.latch_store import call_quietly

log = structlog.get_logger("millsense.history")

COMMIT_INTERVAL_S = 1.0
BATCH_ROWS = 500
QUEUE_ROWS = 4096            # ~7 minutes at 10 revolutions a second; a few MB at worst
BUSY_TIMEOUT_S = 2.0         # a lock held longer than this is a fault (rows dropped), never a wait upstream
REOPEN_S = 5.0               # after a failed open, the writer tries again this often
MAINTENANCE_S = 60.0         # retention runs this often (by the store's clock)
OTHER_RETENTION_FACTOR = 10  # processes and alarms are kept this many times retention_days
WAL_LIMIT_BYTES = 4 << 20    # the -wal file is truncated to this after a checkpoint
# The writer's page cache. SQLite's default (2000 KiB) fills at open on any history past 2 MB, as
# `quick_check` reads every page, and stays resident (issue 13: RSS). The writer appends at the
# right edge of a few b-trees and deletes by time once a minute: 512 KiB holds that working set.
CACHE_KIB = 512

_WAKE = object()             # ends the batch being gathered now (limits to save, close)


def _sqlite_name(exc: BaseException) -> str:
    return getattr(exc, "sqlite_errorname", "") or type(exc).__name__


def describe(exc: BaseException, path: Path) -> str:
    """One line for an operator: what failed, where, and what it means for monitoring."""
    name = _sqlite_name(exc)
    if name == "SQLITE_FULL":
        what = "the disk is full"
    elif name.startswith("SQLITE_BUSY") or name.startswith("SQLITE_LOCKED"):
        what = f"the database is locked by another program for more than {BUSY_TIMEOUT_S:g} s"
    elif name.startswith("SQLITE_READONLY") or name.startswith("SQLITE_CANTOPEN"):
        what = "the file cannot be written (permissions or a read-only disk)"
    elif name.startswith("SQLITE_IOERR"):
        what = "an I/O error"
    else:
        what = "an error"
    return (f"history database {path}: {what} ({name}: {exc}); history rows are dropped and counted "
            "until it is fixed, monitoring goes on")


def _is_corruption(exc: BaseException) -> bool:
    return _sqlite_name(exc).startswith(("SQLITE_CORRUPT", "SQLITE_NOTADB"))


class _Corrupt(Exception):
    pass


class HistoryStore:
    """The history of one machine. `add_*` and `save_*` are thread-safe and never block."""

    def __init__(self, path: Path, *, machine: str, retention_days: float = 30, max_mb: float = 500,
                 keep_revolutions: bool = True, on_error: Callable[[str], Any] | None = None,
                 on_ok: Callable[[], Any] | None = None, clock: Callable[[], float] = time.time):
        self.path = Path(path)
        self.machine = machine
        self.retention_s = float(retention_days) * 86400.0
        self.max_bytes = int(float(max_mb) * 1_000_000)
        self.keep_revolutions = keep_revolutions
        self._on_error = on_error
        self.on_ok = on_ok
        self.clock = clock
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_ROWS)
        self._cond = threading.Condition()
        self._limits: dict[str, dict] = {}
        self._tools: dict | None = None
        self._conn: sqlite3.Connection | None = None
        self._thread: threading.Thread | None = None
        self._closing = False
        self._refused: str | None = None  # a newer schema: never retried
        self._last_open_try = 0.0
        self._last_maintenance: float | None = None
        self._faulted = False
        self._accepted = 0
        self._handled = 0
        self._cycles = 0  # rounds of the writer completed
        self.written = {"revolutions": 0, "processes": 0, "alarms": 0, "limits": 0, "tools": 0}
        self.dropped = 0
        self.dropped_queue_full = 0  # of `dropped`: refused at once because the writer was behind
        self.deleted = {"retention": 0, "size_cap": 0}
        self.errors = 0
        self.last_error: str | None = None
        self.moved_aside: list[str] = []

    @property
    def on_error(self) -> Callable[[str], Any] | None:
        return self._on_error

    @on_error.setter
    def on_error(self, fn: Callable[[str], Any] | None) -> None:
        """A callback set after a failed `start()` (the runner sets its own once it exists) still
        hears of the fault under way: it is called at once with its reason."""
        with self._cond:
            self._on_error = fn
            pending = self.last_error if self._faulted else None
        if pending is not None:
            self._call(fn, pending)

    # -- life -----------------------------------------------------------------------
    def start(self) -> None:
        """Open (or create, or migrate, or replace a damaged) file, then start the writer.

        Never raises: a file that cannot be opened is a fault through `on_error`,
        and the writer tries again every `REOPEN_S` (a newer schema is not retried).
        """
        self._try_open()
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="millsense-history", daemon=True)
            self._thread.start()

    def close(self, timeout_s: float = 2.0) -> None:
        """Write what is queued (within `timeout_s`), then close the file."""
        with self._cond:
            self._closing = True
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if not self._thread.is_alive():
                self._thread = None
        elif self._conn is not None:
            self._conn.close()
            self._conn = None

    def flush(self, timeout_s: float = 5.0) -> bool:
        """Wait (bounded) until everything added so far is written or dropped, and one round of
        the writer (its retention and size cap included) has ended after the call. True if so."""
        with self._cond:
            target, cycle = self._accepted, self._cycles
        self._wake()
        with self._cond:
            return self._cond.wait_for(lambda: self._thread is None or (
                self._handled >= target and self._cycles > cycle and not self._limits and self._tools is None),
                timeout_s)

    # -- adding (any thread, never blocks) ----------------------------------------------
    def add_revolution(self, estimate: dict) -> None:
        if self.keep_revolutions:
            self._put("revolutions", records.revolution_row, estimate)

    def add_process(self, summary: dict) -> None:
        self._put("processes", records.process_row, summary)

    def add_alarm(self, alarm: dict) -> None:
        self._put("alarms", records.alarm_row, alarm)

    def save_limits(self, key: str, data: dict) -> None:
        """Upsert the learned limits of a process key; on disk within one commit (synchronous FULL)."""
        with self._cond:
            self._limits[str(key)] = dict(data)
        self._wake()

    def save_tools(self, data: dict) -> None:
        with self._cond:
            self._tools = dict(data)
        self._wake()

    def _put(self, table: str, to_row: Callable[[dict, float], tuple], payload: dict) -> None:
        # The row is made here, in the caller's thread (a few µs): the queue then holds small tuples,
        # not the payload dicts (a full queue stays within a few MB), and a caller may reuse its dict.
        try:
            item = (table, to_row(payload, self.clock()))
        except Exception as exc:  # noqa: BLE001 - a malformed payload is one dropped row, never the caller's error
            log.error("history.bad_payload", table=table, error=f"{type(exc).__name__}: {exc}")
            with self._cond:
                self.dropped += 1
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            with self._cond:
                self.dropped += 1
                self.dropped_queue_full += 1
            return
        with self._cond:
            self._accepted += 1

    def _wake(self) -> None:
        try:
            self._queue.put_nowait(_WAKE)
        except queue.Full:
            pass  # a full queue ends the batch by its size anyway

    # -- reading, at start ----------------------------------------------------------------
    def load_limits(self) -> dict[str, Any]:
        """Every stored key's learned limits as stored: a JSON value, or `records.UnreadableRow` for a row that is
        not JSON. Never raises for a row: the learning checks each and sets aside what fails (docs/learning.md)."""
        return {str(key): records.stored_value(text)
                for key, text in self._read("SELECT key, payload FROM limits ORDER BY key")}

    def load_tools(self) -> Any:
        """The stored tool table (a JSON value, or UnreadableRow), {} when there is none."""
        rows = self._read("SELECT payload FROM tools WHERE id = 1")
        return records.stored_value(rows[0][0]) if rows else {}

    def last_process_id(self) -> int:
        """The highest process id in the history (0: none), so that ids go on across restarts."""
        rows = self._read("SELECT max(CAST(json_extract(payload, '$.process') AS INTEGER)) FROM processes")
        return int(rows[0][0]) if rows and rows[0][0] is not None else 0

    def _read(self, sql: str) -> list[tuple]:
        """A read on its own connection (WAL lets it run beside the writer); [] when there is no file."""
        if not self.path.exists() or self._refused:
            return []
        try:
            conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, timeout=BUSY_TIMEOUT_S)
            try:
                return conn.execute(sql).fetchall()
            finally:
                conn.close()
        except sqlite3.Error as exc:
            log.error("history.read_failed", path=str(self.path), error=f"{_sqlite_name(exc)}: {exc}")
            return []

    def stats(self) -> dict[str, Any]:
        with self._cond:
            out = {
                "path": str(self.path), "open": self._conn is not None, "fault": self._faulted,
                "schema_version": SCHEMA_VERSION, "written": dict(self.written), "dropped": self.dropped,
                "dropped_queue_full": self.dropped_queue_full,
                "deleted": dict(self.deleted), "queued": self._queue.qsize(), "errors": self.errors,
                "last_error": self.last_error, "moved_aside": list(self.moved_aside),
            }
        out["db_bytes"] = sum(_size(self.path.with_name(self.path.name + s)) for s in ("", "-wal", "-shm"))
        return out

    # -- opening --------------------------------------------------------------------------
    def _try_open(self) -> None:
        self._last_open_try = time.monotonic()
        try:
            try:
                self._conn = self._open()
            except _Corrupt as exc:
                self._move_aside(str(exc))
                self._conn = self._open()
            self._recovered()  # an open that works ends a fault of an earlier try
        except NewerSchemaError as exc:
            self._refused = str(exc)
            log.error("history.newer_schema", path=str(self.path), error=str(exc))
            self._fail(f"{exc}; no history is written, monitoring goes on")
        except (sqlite3.Error, OSError, _Corrupt) as exc:
            self._fail(describe(exc, self.path))

    def _open(self) -> sqlite3.Connection:
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        new = not self.path.exists() or self.path.stat().st_size == 0
        conn = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False)
        try:
            if new:
                conn.execute("PRAGMA auto_vacuum = INCREMENTAL")  # only before the first table
            check_version(version_of(conn), str(self.path))  # before anything is written: a newer file stays as it is
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise sqlite3.OperationalError(f"journal_mode WAL refused (got {mode})")
            conn.execute("PRAGMA synchronous = FULL")
            conn.execute(f"PRAGMA cache_size = {-CACHE_KIB}")  # negative: KiB, not pages
            conn.execute(f"PRAGMA journal_size_limit = {WAL_LIMIT_BYTES}")
            check = conn.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise _Corrupt(f"quick_check: {check}")
            applied = migrate(conn, str(self.path))
            conn.execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('machine', ?)", (self.machine,))
        except sqlite3.DatabaseError as exc:
            conn.close()
            if _is_corruption(exc):
                raise _Corrupt(f"{_sqlite_name(exc)}: {exc}") from None
            raise
        except BaseException:
            conn.close()
            raise
        log.info("history.opened", path=str(self.path), new=new, migrated_to=applied or None)
        return conn

    def _move_aside(self, why: str) -> None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        n = 1
        while aside.exists():  # a second damaged file within the second: never over the first
            n += 1
            aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{n}")
        for suffix in ("", "-wal", "-shm"):
            src = self.path.with_name(self.path.name + suffix)
            if src.exists():
                os.replace(src, aside.with_name(aside.name + suffix))
        self.moved_aside.append(str(aside))
        log.error("history.corrupt_moved_aside", path=str(self.path), moved_to=str(aside), reason=why)

    # -- the writer thread ----------------------------------------------------------------
    def _run(self) -> None:
        from millsense.drivers.base import name_os_thread

        name_os_thread("ms-history")
        try:
            while True:
                batch, closing = self._gather()
                if self._conn is None and not self._refused and time.monotonic() - self._last_open_try >= REOPEN_S:
                    self._try_open()
                self._write(batch)
                if self._conn is not None:
                    self._maintain()
                with self._cond:
                    self._cycles += 1
                    self._cond.notify_all()
                if closing:
                    return
        finally:
            if self._conn is not None:
                self._conn.close()  # the last connection checkpoints the WAL into the file
                self._conn = None
            with self._cond:
                self._cond.notify_all()

    def _gather(self) -> tuple[list[tuple[str, tuple]], bool]:
        """What arrives within one commit interval (or BATCH_ROWS, or until woken)."""
        batch: list[tuple[str, tuple]] = []
        deadline = time.monotonic() + COMMIT_INTERVAL_S
        while len(batch) < BATCH_ROWS:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                item = self._queue.get(timeout=remaining)
            except queue.Empty:
                break
            if item is _WAKE:
                break
            batch.append(item)
        with self._cond:
            closing = self._closing
        if closing:  # drain what is queued: close() waits for it (bounded by its timeout)
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is not _WAKE:
                    batch.append(item)
        return batch, closing

    def _write(self, batch: list[tuple[str, tuple]]) -> None:
        with self._cond:
            limits, self._limits = self._limits, {}
            tools, self._tools = self._tools, None
        if not batch and not limits and tools is None:
            return
        now = self.clock()
        rows: dict[str, list[tuple]] = {"revolutions": [], "processes": [], "alarms": []}
        for table, row in batch:
            rows[table].append(row)
        conn = self._conn
        try:
            if conn is None:
                raise sqlite3.OperationalError(self.last_error or "history database not open")
            conn.execute("BEGIN IMMEDIATE")
            try:
                conn.executemany(records.INSERT_REVOLUTION, rows["revolutions"])
                conn.executemany(records.INSERT_PROCESS, rows["processes"])
                conn.executemany(records.INSERT_ALARM, rows["alarms"])
                conn.executemany(records.UPSERT_LIMITS,
                                 [(k, now, records.payload_json(v)) for k, v in limits.items()])
                if tools is not None:
                    conn.execute(records.UPSERT_TOOLS, (now, records.payload_json(tools)))
                conn.execute("COMMIT")
            except BaseException:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            with self._cond:
                self.dropped += len(batch)
                self._handled += len(batch)
                for k, v in limits.items():  # learned limits are never dropped: kept for the next commit
                    self._limits.setdefault(k, v)
                if tools is not None and self._tools is None:
                    self._tools = tools
                self._cond.notify_all()
            if conn is not None:
                log.error("history.write_failed", path=str(self.path), rows=len(batch),
                          error=f"{_sqlite_name(exc)}: {exc}")
                self._fail(describe(exc, self.path))
                if _is_corruption(exc):
                    conn.close()  # reopened later: the quick check moves the damaged file aside
                    self._conn = None
            return
        with self._cond:
            for table, r in rows.items():
                self.written[table] += len(r)
            self.written["limits"] += len(limits)
            self.written["tools"] += int(tools is not None)
            self._handled += len(batch)
            self._cond.notify_all()
        self._recovered()

    # -- retention and the size cap -------------------------------------------------------
    def _maintain(self) -> None:
        try:
            now = self.clock()
            if self._last_maintenance is None or now - self._last_maintenance >= MAINTENANCE_S:
                self._last_maintenance = now
                n = bounds.delete_older(self._conn, "revolutions", now - self.retention_s)
                for table in ("processes", "alarms"):
                    n += bounds.delete_older(self._conn, table, now - self.retention_s * OTHER_RETENTION_FACTOR)
                if n:
                    log.info("history.retention", deleted=n)
                self.deleted["retention"] += n
            n = bounds.enforce_cap(self._conn, self.max_bytes)
            if n:
                self.deleted["size_cap"] += n
                log.info("history.size_cap", deleted=n, max_mb=self.max_bytes / 1e6)
        except sqlite3.Error as exc:
            self._fail(describe(exc, self.path))

    # -- faults ---------------------------------------------------------------------------
    def _fail(self, reason: str) -> None:
        with self._cond:
            self.errors += 1
            self.last_error = reason
            first = not self._faulted
            self._faulted = True
        if first:
            log.error("history.fault", path=str(self.path), reason=reason)
            self._call(self._on_error, reason)

    def _recovered(self) -> None:
        with self._cond:
            was = self._faulted
            self._faulted = False
        if was:
            log.info("history.recovered", path=str(self.path))
            self._call(self.on_ok)

    @staticmethod
    def _call(fn: Callable[..., Any] | None, *args: Any) -> None:
        call_quietly(fn, "history.callback_failed", *args)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0
