"""Reading the history back out: rows of one table, filtered, as CSV or JSON lines.

Read-only: the file is opened with `mode=ro`, so an export runs beside the
daemon that writes it (WAL: a reader sees the last commit and never blocks
the writer) and can never change or lock it for writing.
"""

from __future__ import annotations

import csv
import json
import os
import sqlite3
from pathlib import Path
from typing import Any, Iterator, TextIO

from millsense.daemon.history.records import UnreadableRow, stored_value
from millsense.daemon.history.schema import REVOLUTION_COLUMNS, check_version, version_of

TABLES = ("revolutions", "processes", "alarms", "limits")

# The CSV columns of the tables that keep whole payloads (brief14's shapes); JSON lines carry the whole payload.
PROCESS_FIELDS = ("machine", "t", "process", "key", "program", "tool", "operation", "revolutions",
                  "cutting_revolutions", "entry_rev", "torque_peak_nm", "torque_mean_nm", "force_peak_n",
                  "energy_j", "verdict", "learned", "learn_target", "envelope", "energy_ratio",
                  "tool_processes", "tool_wear_pct")
ALARM_FIELDS = ("machine", "t", "rev", "level", "quantity", "value", "limit", "interlock", "program", "tool",
                "operation", "process", "process_rev")
LIMIT_FIELDS = ("key", "t", "program", "tool", "operation", "payload")
REVOLUTION_FIELDS = ("machine",) + REVOLUTION_COLUMNS
BOOLEAN_COLUMNS = ("cutting", "valid")


class ExportError(RuntimeError):
    """The file cannot be read (missing, damaged, newer): one line for the user."""


def open_read_only(path: Path) -> sqlite3.Connection:
    if not Path(path).is_file():
        raise ExportError(f"no history database at {path} (is [history] enabled, and has the daemon run?)")
    try:
        conn = sqlite3.connect(f"file:{os.fspath(path)}?mode=ro", uri=True, timeout=2.0)
        check_version(version_of(conn), str(path))
    except sqlite3.Error as exc:
        raise ExportError(f"{path} cannot be read as a history database: {exc}") from None
    except RuntimeError as exc:  # NewerSchemaError
        raise ExportError(str(exc)) from None
    return conn


def _machine(conn: sqlite3.Connection) -> str | None:
    row = conn.execute("SELECT value FROM meta WHERE key = 'machine'").fetchone()
    return row[0] if row else None


def _columns(conn: sqlite3.Connection, table: str) -> set[str]:
    return {row[1] for row in conn.execute(f"PRAGMA table_info({table})")}


def rows(conn: sqlite3.Connection, what: str, *, t_from: float | None = None, t_to: float | None = None,
         program: int | None = None, tool: int | None = None, operation: int | None = None) -> Iterator[dict[str, Any]]:
    """The rows of `what` in time order, as dicts (payload tables: the whole payload, with `t`)."""
    machine = _machine(conn)
    if what == "limits":
        yield from _limits(conn, program, tool, operation)
        return
    have = _columns(conn, what)
    where, args = [], []
    for column, op, value in (("t", ">=", t_from), ("t", "<", t_to), ("program", "=", program),
                              ("tool", "=", tool), ("operation", "=", operation)):
        if value is None:
            continue
        if column not in have:  # an older file without context columns: nothing can match
            return
        where.append(f"{column} {op} ?")
        args.append(value)
    clause = f" WHERE {' AND '.join(where)}" if where else ""
    if what == "revolutions":
        selected = [c if c in have else f"NULL AS {c}" for c in REVOLUTION_COLUMNS]
        cursor = conn.execute(f"SELECT {', '.join(selected)} FROM revolutions{clause} ORDER BY t, id", args)
        for values in cursor:
            row = {"machine": machine, **dict(zip(REVOLUTION_COLUMNS, values))}
            for name in BOOLEAN_COLUMNS:
                if row[name] is not None:
                    row[name] = bool(row[name])
            yield row
        return
    cursor = conn.execute(f"SELECT t, payload FROM {what}{clause} ORDER BY t, id", args)
    for t, payload in cursor:
        data = json.loads(payload)
        yield {"machine": machine, **data, "t": t} if isinstance(data, dict) else {"machine": machine, "t": t}


def _limits(conn, program, tool, operation) -> Iterator[dict[str, Any]]:
    for key, t, payload in conn.execute("SELECT key, t, payload FROM limits ORDER BY key"):
        parts = (str(key).split("/") + [None, None, None])[:3]
        numbers = [int(p) if p is not None and p.isdigit() else None for p in parts]
        wanted = (program, tool, operation)
        if any(w is not None and n != w for w, n in zip(wanted, numbers)):
            continue
        value = stored_value(payload)   # a row that is not JSON is exported as what it is, never an error
        if isinstance(value, UnreadableRow):
            value = {"unreadable": str(value), "text": value.text}
        yield {"key": key, "t": t, "program": numbers[0], "tool": numbers[1], "operation": numbers[2],
               "payload": value}


def fields_of(what: str) -> tuple[str, ...]:
    return {"revolutions": REVOLUTION_FIELDS, "processes": PROCESS_FIELDS, "alarms": ALARM_FIELDS,
            "limits": LIMIT_FIELDS}[what]


def write(out: TextIO, what: str, items: Iterator[dict[str, Any]], fmt: str) -> int:
    """Write the rows; the count."""
    return write_rows(out, fields_of(what), items, fmt)


def write_rows(out: TextIO, fields: list[str], items: Iterator[dict[str, Any]], fmt: str) -> int:
    """JSON lines, or CSV with `fields` as its header (the plant's history reads out the same way); the count."""
    n = 0
    if fmt == "jsonl":
        for item in items:
            out.write(json.dumps(item, separators=(",", ":"), allow_nan=False) + "\n")
            n += 1
        return n
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(fields)
    for item in items:
        writer.writerow([_cell(item.get(name)) for name in fields])
        n += 1
    return n


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(",", ":"))
    return str(value)
