"""The history database's schema: a version table and the ordered migrations that reach it.

Each migration is a list of statements run in one transaction together with the
row that records it in `schema_version`; a file is brought from whatever
version it holds to `SCHEMA_VERSION` one step at a time, so a daemon of a later
release opens an older file and keeps its rows. A file written by a *newer*
release is refused (`NewerSchemaError`): its tables may mean something this
code cannot know, and writing into them could lose data the newer release
depends on.

Column choice (bytes matter: a machine at 10 revolutions a second writes
864 000 revolutions a day). A revolution keeps the numbers an export or a
plot needs, as columns (REAL/INTEGER, no JSON): about 110 bytes a row with its
time index, measured by tests/history/test_store.py. Processes, alarms, limits
and tools are few; they keep their whole payload as JSON beside the columns
that exports filter on.
"""

from __future__ import annotations

import sqlite3
import time

SCHEMA_VERSION = 2


class NewerSchemaError(RuntimeError):
    """The file was written by a newer millsense (its schema version is above ours)."""


# The per-revolution columns, in table order, and the estimate key each comes from.
REVOLUTION_COLUMNS_V1 = (
    "t", "rev", "spindle_rpm", "torque_nm", "torque_sigma_nm", "force_n", "axial_depth_mm",
    "radial_depth_mm", "feed_per_tooth_mm", "p_in_w", "cutting", "valid",
)
REVOLUTION_COLUMNS_V2 = ("program", "tool", "operation", "process_rev", "envelope_low_nm", "envelope_high_nm")
REVOLUTION_COLUMNS = REVOLUTION_COLUMNS_V1 + REVOLUTION_COLUMNS_V2

# version -> (what it brings, statements)
MIGRATIONS: dict[int, tuple[str, tuple[str, ...]]] = {
    1: ("first shape: revolutions, processes, alarms, learned limits, tools", (
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
        "CREATE TABLE revolutions (id INTEGER PRIMARY KEY, t REAL NOT NULL, rev INTEGER, spindle_rpm REAL, "
        "torque_nm REAL, torque_sigma_nm REAL, force_n REAL, axial_depth_mm REAL, radial_depth_mm REAL, "
        "feed_per_tooth_mm REAL, p_in_w REAL, cutting INTEGER, valid INTEGER)",
        "CREATE INDEX revolutions_t ON revolutions (t)",
        "CREATE TABLE processes (id INTEGER PRIMARY KEY, t REAL NOT NULL, key TEXT, program INTEGER, "
        "tool INTEGER, operation INTEGER, verdict TEXT, payload TEXT NOT NULL)",
        "CREATE INDEX processes_t ON processes (t)",
        "CREATE TABLE alarms (id INTEGER PRIMARY KEY, t REAL NOT NULL, rev INTEGER, level TEXT, "
        "program INTEGER, tool INTEGER, operation INTEGER, payload TEXT NOT NULL)",
        "CREATE INDEX alarms_t ON alarms (t)",
        "CREATE TABLE limits (key TEXT PRIMARY KEY, t REAL NOT NULL, payload TEXT NOT NULL)",
        "CREATE TABLE tools (id INTEGER PRIMARY KEY CHECK (id = 1), t REAL NOT NULL, payload TEXT NOT NULL)",
    )),
    2: ("context per revolution: program, tool, operation, process_rev, envelope", tuple(
        f"ALTER TABLE revolutions ADD COLUMN {name} {'REAL' if name.startswith('envelope') else 'INTEGER'}"
        for name in REVOLUTION_COLUMNS_V2
    ) + ("CREATE INDEX processes_key ON processes (key)",)),
}

VERSION_TABLE = ("CREATE TABLE IF NOT EXISTS schema_version "
                 "(version INTEGER PRIMARY KEY, applied_t REAL NOT NULL, description TEXT NOT NULL)")


def version_of(conn: sqlite3.Connection) -> int:
    """The schema version a file holds: 0 for an empty (new) file."""
    row = conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name = 'schema_version'").fetchone()
    if row is None:
        return 0
    (version,) = conn.execute("SELECT COALESCE(MAX(version), 0) FROM schema_version").fetchone()
    return int(version)


def check_version(version: int, where: str) -> None:
    if version > SCHEMA_VERSION:
        raise NewerSchemaError(
            f"{where} has history schema version {version}, newer than this millsense's {SCHEMA_VERSION}: "
            "it was written by a later release; upgrade millsense, or set [history] path to another file"
        )


def migrate(conn: sqlite3.Connection, where: str, upto: int = SCHEMA_VERSION) -> list[int]:
    """Bring the file to version `upto` (each step in its own transaction). The versions applied.

    `conn` must be in autocommit mode (isolation_level=None): the transactions are explicit.
    """
    conn.execute(VERSION_TABLE)
    current = version_of(conn)
    check_version(current, where)
    applied = []
    for version in range(current + 1, upto + 1):
        description, statements = MIGRATIONS[version]
        conn.execute("BEGIN IMMEDIATE")
        try:
            for statement in statements:
                conn.execute(statement)
            conn.execute("INSERT INTO schema_version (version, applied_t, description) VALUES (?, ?, ?)",
                         (version, time.time(), description))
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        applied.append(version)
    return applied
