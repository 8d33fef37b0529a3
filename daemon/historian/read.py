"""`millsense history --dsn`: the plant's database read back (docs/historian.md), the rows of one table across
machines and a time range, as CSV or JSON lines; times in UTC, ISO 8601 with its offset (`+00:00`).

The connection is read-only (`default_transaction_read_only`): the Grafana role of docs/historian.md is enough.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any, TextIO

import psycopg
from psycopg import sql

from millsense.daemon.historian.schema import column_names
from millsense.daemon.history.export import write_rows

# --what → table (the SQLite export's names, and the tables only the plant's database has)
TABLE_OF = {"revolutions": "revolutions", "processes": "processes", "alarms": "alarms", "limits": "limit_changes",
            "load": "load_1s", "status": "status_changes"}


def connect(dsn: str, passfile: str | None) -> psycopg.Connection:
    extra: dict[str, Any] = {"connect_timeout": 10, "application_name": "millsense-history",
                             "options": "-c default_transaction_read_only=on -c timezone=UTC"}
    if passfile:
        extra["passfile"] = passfile
    return psycopg.connect(dsn, **extra)


def fields_of(what: str) -> list[str]:
    return column_names(TABLE_OF[what])


def rows(conn: psycopg.Connection, what: str, *, machines: list[str] | None, t_from: float | None,
         t_to: float | None, **numbers: int | None) -> Iterator[dict[str, Any]]:
    table = TABLE_OF[what]
    names = column_names(table)
    where, params = [], []
    if machines:
        where.append(sql.SQL("machine = ANY(%s)"))
        params.append(list(machines))
    if t_from is not None:
        where.append(sql.SQL("time >= %s"))
        params.append(datetime.fromtimestamp(t_from, UTC))
    if t_to is not None:
        where.append(sql.SQL("time < %s"))
        params.append(datetime.fromtimestamp(t_to, UTC))
    for name, value in numbers.items():
        if value is not None:
            where.append(sql.SQL("{} = %s").format(sql.Identifier(name)))
            params.append(value)
    query = sql.SQL("SELECT {cols} FROM {t}{w} ORDER BY time, machine").format(
        cols=sql.SQL(", ").join(map(sql.Identifier, names)), t=sql.Identifier(table),
        w=sql.SQL(" WHERE ") + sql.SQL(" AND ").join(where) if where else sql.SQL(""))
    with conn.cursor(name="history_export") as cur:   # server-side: a year of rows is not held in memory
        cur.execute(query, params)
        for values in cur:
            yield {n: _value(v) for n, v in zip(names, values)}


def _value(v: Any) -> Any:
    if isinstance(v, datetime):
        return v.astimezone(UTC).isoformat()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def write(out: TextIO, what: str, items: Iterator[dict[str, Any]], fmt: str) -> int:
    """The rows as `millsense history` writes the machine's own (history/export.py); the count."""
    return write_rows(out, fields_of(what), items, fmt)
