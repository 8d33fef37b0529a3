"""The historian's schema: its tables, day partitions, retention, and the schema's version (docs/historian.md).

Every table has `time` (timestamptz, UTC: the daemon's clock, the payload's `t`), `received_at` (the historian's
clock) and `machine`, then the payload's fields as typed columns, and is partitioned by day on `time`
(PostgreSQL's declarative range partitioning: retention drops whole partitions, never deletes rows). A DEFAULT
partition catches what no day partition takes. Unique keys include `time` (a unique index of a partitioned table
must hold its partition key) and make a replay idempotent (`INSERT … ON CONFLICT DO NOTHING`).

The database records its version in `schema_version`. `ensure_schema` makes a new database, upgrades an older one
in one transaction (`UPGRADES[v]`: the statements from v to v + 1), and refuses a newer one: a historian must not
write into tables whose meaning it does not know.
"""

from __future__ import annotations

import re
from datetime import UTC, date, datetime, timedelta
from typing import Any

from psycopg import sql

SCHEMA_VERSION = 2
# The columns a version added to `limit_changes` (version 2: the operator's published changes, `limits/change`).
# An upgrade only ever appends columns, at the end: a row spooled by an older historian is the same row with the
# new columns null (writer.py pads it).
_LIMIT_CHANGES_V2 = [("action", "text"), ("pct", "double precision"), ("requester", "text"),
                     ("authority", "text"), ("before", "jsonb"), ("after", "jsonb"), ("payload", "jsonb")]
# UPGRADES[v]: the statements taking a database of version v to v + 1, run in one transaction with the version's
# update (tests/historian/test_schema.py upgrades version 1's dump, tests/historian/schema_v1.sql).
UPGRADES: dict[int, list[str]] = {
    1: ["ALTER TABLE limit_changes " + ", ".join(f"ADD COLUMN {name} {kind}" for name, kind in _LIMIT_CHANGES_V2)],
}
DAYS_AHEAD = 2   # day partitions made at least this far ahead of today (UTC)

_T = [("time", "timestamptz NOT NULL"), ("received_at", "timestamptz NOT NULL"), ("machine", "text NOT NULL")]

# table -> (columns after the common three, the unique key's columns, extra indexes' columns)
TABLES: dict[str, tuple[list[tuple[str, str]], tuple[str, ...], list[tuple[str, ...]]]] = {
    "alarms": ([
        ("level", "text NOT NULL"), ("quantity", "text"), ("value", "double precision"),
        ("limit_value", "double precision"), ("interlock", "text"), ("rev", "bigint"), ("run_id", "text"),
        ("alarm_seq", "bigint"), ("program", "bigint"), ("tool", "bigint"), ("operation", "integer"),
        ("process", "bigint"), ("process_rev", "bigint"), ("expected", "double precision"), ("reason", "text"),
        ("payload", "jsonb NOT NULL"),
    ], ("machine", "time", "level", "quantity", "alarm_seq"), [("level", "time")]),
    "processes": ([
        ("process", "bigint"), ("key", "text"), ("program", "bigint"), ("tool", "bigint"), ("operation", "integer"),
        ("revolutions", "bigint"), ("cutting_revolutions", "bigint"), ("entry_rev", "bigint"),
        ("torque_peak_nm", "double precision"), ("torque_mean_nm", "double precision"),
        ("force_peak_n", "double precision"), ("energy_j", "double precision"), ("verdict", "text"),
        ("learned", "integer"), ("learn_target", "integer"), ("envelope", "text"),
        ("energy_ratio", "double precision"), ("tool_processes", "bigint"), ("tool_wear_pct", "double precision"),
        ("expected_band", "text"), ("payload", "jsonb NOT NULL"),
    ], ("machine", "time", "process"), [("program", "tool", "operation", "time")]),
    "status_changes": ([
        ("state", "text"), ("daq_link", "text"), ("interlock", "text"), ("alarm", "text"), ("faults", "jsonb"),
        ("run_id", "text"), ("payload", "jsonb NOT NULL"),
    ], ("machine", "time"), []),
    "limit_changes": ([
        ("key", "text NOT NULL"), ("change", "text NOT NULL"), ("envelope", "text"), ("learned", "integer"),
        ("process", "bigint"), *_LIMIT_CHANGES_V2,
    ], ("machine", "time", "key", "change"), []),
    "load_1s": ([
        ("revolutions", "integer NOT NULL"), ("valid", "integer NOT NULL"), ("invalid", "integer NOT NULL"),
        ("torque_min_nm", "double precision"), ("torque_mean_nm", "double precision"),
        ("torque_max_nm", "double precision"), ("force_min_n", "double precision"),
        ("force_mean_n", "double precision"), ("force_max_n", "double precision"),
        ("power_min_w", "double precision"), ("power_mean_w", "double precision"),
        ("power_max_w", "double precision"),
    ], ("machine", "time"), []),
    "revolutions": ([
        ("rev", "bigint NOT NULL"), ("valid", "boolean NOT NULL"), ("invalid", "text"), ("spindle_rpm", "double precision"),
        ("p_in_w", "double precision"), ("p_gap_w", "double precision"), ("torque_nm", "double precision"),
        ("force_n", "double precision"), ("radial_depth_mm", "double precision"),
        ("axial_depth_mm", "double precision"), ("depth_status", "text"), ("feed_override_pct", "double precision"),
        ("program", "bigint"), ("tool", "bigint"), ("operation", "integer"), ("process_rev", "bigint"),
    ], ("machine", "time", "rev"), []),
}


def columns(table: str) -> list[tuple[str, str]]:
    return _T + TABLES[table][0]


def column_names(table: str) -> list[str]:
    return [name for name, _ in columns(table)]


class SchemaError(RuntimeError):
    """The database's schema cannot be used (a newer version, a failed upgrade): one line, said and exit 1."""


def create_statements() -> list[sql.Composable]:
    out: list[sql.Composable] = [sql.SQL(
        "CREATE TABLE schema_version (version integer NOT NULL, since timestamptz NOT NULL DEFAULT now())")]
    for table, (_, unique, indexes) in TABLES.items():
        cols = sql.SQL(", ").join(sql.SQL("{} {}").format(sql.Identifier(n), sql.SQL(t)) for n, t in columns(table))
        # NULLS NOT DISTINCT (PostgreSQL 15): an alarm without alarm_seq (replay) is still one row, not many
        out.append(sql.SQL("CREATE TABLE {t} ({cols}, UNIQUE NULLS NOT DISTINCT ({u})) PARTITION BY RANGE (time)")
                   .format(t=sql.Identifier(table), cols=cols, u=sql.SQL(", ").join(map(sql.Identifier, unique))))
        out.append(sql.SQL("CREATE TABLE {p} PARTITION OF {t} DEFAULT")
                   .format(p=sql.Identifier(f"{table}_default"), t=sql.Identifier(table)))
        for i, index in enumerate(indexes):
            out.append(sql.SQL("CREATE INDEX {n} ON {t} ({c})").format(
                n=sql.Identifier(f"{table}_i{i}"), t=sql.Identifier(table), c=sql.SQL(", ").join(map(sql.Identifier, index))))
    return out


def stored_version(conn: Any) -> int | None:
    """The database's schema version, None for a database without our tables."""
    with conn.cursor() as cur:
        cur.execute("SELECT to_regclass('schema_version') IS NOT NULL")
        if not cur.fetchone()[0]:
            return None
        cur.execute("SELECT max(version) FROM schema_version")
        row = cur.fetchone()
        return row[0]


def ensure_schema(conn: Any, version: int = SCHEMA_VERSION, upgrades: dict[int, list[str]] | None = None) -> str:
    """Make, check or upgrade the schema; what was done ("created", "current", "upgraded from N"). Raises
    SchemaError for a newer version or an upgrade that fails (the database is then left as it was)."""
    upgrades = UPGRADES if upgrades is None else upgrades
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(4303)")   # two historians starting at once: one makes it
        stored = stored_version(conn)
        if stored is None:
            for statement in create_statements():
                conn.execute(statement)
            conn.execute("INSERT INTO schema_version (version) VALUES (%s)", (version,))
            return "created"
        if stored > version:
            raise SchemaError(f"the database's schema is version {stored}, newer than this historian's {version}: "
                              "upgrade millsense (a historian never writes into tables it does not know)")
        if stored == version:
            return "current"
        try:
            for v in range(stored, version):
                if v not in upgrades:
                    raise SchemaError(f"no upgrade from schema version {v} to {v + 1}")
                for statement in upgrades[v]:
                    conn.execute(statement)
            conn.execute("INSERT INTO schema_version (version) VALUES (%s)", (version,))
        except SchemaError:
            raise
        except Exception as exc:  # noqa: BLE001 - the transaction rolls back; one line for the log
            raise SchemaError(f"upgrading the schema from version {stored} to {version} failed, nothing changed: "
                              f"{type(exc).__name__}: {str(exc).strip().splitlines()[0]}") from None
        return f"upgraded from {stored}"


def partition_name(table: str, day: date) -> str:
    return f"{table}_p{day:%Y%m%d}"


_PARTITION_RE = re.compile(r"^(?P<table>[a-z_0-9]+)_p(?P<day>\d{8})\Z")


def ensure_partitions(conn: Any, table: str, days: set[date] | list[date]) -> list[str]:
    """Day partitions of `table` for `days` (those missing are made, each in its own transaction); their names."""
    made = []
    existing = set(partitions(conn, table))
    for day in sorted(set(days)):
        if day in existing:
            continue
        start = datetime(day.year, day.month, day.day, tzinfo=UTC)
        with conn.transaction():   # bounds are DDL (no parameters): literals of our own datetimes
            conn.execute(sql.SQL("CREATE TABLE IF NOT EXISTS {p} PARTITION OF {t} FOR VALUES FROM ({a}) TO ({b})").format(
                p=sql.Identifier(partition_name(table, day)), t=sql.Identifier(table),
                a=sql.Literal(start), b=sql.Literal(start + timedelta(days=1))))
        made.append(partition_name(table, day))
    return made


def ahead(today: date) -> list[date]:
    return [today + timedelta(days=i) for i in range(DAYS_AHEAD + 1)]


def partitions(conn: Any, table: str) -> dict[date, str]:
    """The day partitions of `table` (the DEFAULT one is not among them)."""
    with conn.cursor() as cur:
        cur.execute("SELECT c.relname FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid "
                    "WHERE i.inhparent = to_regclass(%s)", (table,))
        out = {}
        for (name,) in cur.fetchall():
            m = _PARTITION_RE.match(name)
            if m and m["table"] == table:
                out[datetime.strptime(m["day"], "%Y%m%d").date()] = name
        return out


def drop_expired(conn: Any, table: str, keep_from: datetime) -> list[str]:
    """Drop the day partitions of `table` wholly before `keep_from`; their names."""
    dropped = []
    for day, name in sorted(partitions(conn, table).items()):
        if datetime(day.year, day.month, day.day, tzinfo=UTC) + timedelta(days=1) <= keep_from:
            with conn.transaction():
                conn.execute(sql.SQL("DROP TABLE {}").format(sql.Identifier(name)))
            dropped.append(name)
    return dropped
