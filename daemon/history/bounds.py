"""Keeping the history file bounded: rows past their retention, and the size cap.

Plain functions on the writer's connection (autocommit: each DELETE is its own
short transaction, so a reader or the next batch never waits long). Rows go
oldest first; ids grow by one a row, so "oldest" is the smallest id and a
table's row count is max(id) − min(id) + 1 without a scan.
"""

from __future__ import annotations

import sqlite3

DELETE_CHUNK = 5000   # rows per delete transaction
CAP_LOW_WATER = 0.9   # the size cap deletes down to this fraction of the cap
CAP_TABLES = ("revolutions", "processes", "alarms")  # in the order they give way; limits and tools never


def delete_older(conn: sqlite3.Connection, table: str, cut: float) -> int:
    """Delete the rows of `table` older than `cut` (Unix seconds); how many."""
    total = 0
    while True:
        n = conn.execute(f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} WHERE t < ? ORDER BY t LIMIT ?)",
                         (cut, DELETE_CHUNK)).rowcount
        total += n
        if n < DELETE_CHUNK:
            return total


def used_bytes(conn: sqlite3.Connection) -> int:
    """Bytes in pages that hold data (the file less its free pages)."""
    page = conn.execute("PRAGMA page_size").fetchone()[0]
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    free = conn.execute("PRAGMA freelist_count").fetchone()[0]
    return (pages - free) * page


def enforce_cap(conn: sqlite3.Connection, max_bytes: int) -> int:
    """Above `max_bytes` of data, delete oldest rows (revolutions, then processes, then alarms) down to
    CAP_LOW_WATER of it; then shrink a file far above the cap. The rows deleted."""
    deleted = 0
    if used_bytes(conn) > max_bytes:
        target = max_bytes * CAP_LOW_WATER
        for table in CAP_TABLES:
            while (used := used_bytes(conn)) > target:
                n = conn.execute(f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} ORDER BY id LIMIT ?)",
                                 (_chunk(conn, table, used, target),)).rowcount
                deleted += n
                if n == 0:
                    break
    shrink(conn, max_bytes)
    return deleted


def _chunk(conn: sqlite3.Connection, table: str, used: float, target: float) -> int:
    """Rows of `table` to delete for `used` to reach `target`, were the file all this table: never too
    many (the loop deletes again when it was too few)."""
    lo, hi = conn.execute(f"SELECT MIN(id), MAX(id) FROM {table}").fetchone()
    if lo is None:
        return 0
    rows = hi - lo + 1
    return max(1, min(DELETE_CHUNK, int(rows * (used - target) / used) + 1))


def shrink(conn: sqlite3.Connection, max_bytes: int) -> None:
    """Give free pages back only when the file is well above the cap (a cap lowered): within the
    headroom the cap deletes into, free pages are reused, so the file neither grows nor churns."""
    page = conn.execute("PRAGMA page_size").fetchone()[0]
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    if pages * page > max_bytes * (2 - CAP_LOW_WATER):
        over = pages - max_bytes // page
        # executescript steps the pragma to its end; execute() would free one page per call
        conn.executescript(f"PRAGMA incremental_vacuum({int(over)});")
