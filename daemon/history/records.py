"""Payloads (brief14's Zenoh shapes) to table rows, and the rows an export reads back.

A revolution becomes a tuple of plain numbers (no JSON: it is the bulk of the
file); a process, an alarm, learned limits and the tool table keep their whole
payload as strict JSON beside the columns an export filters on.
"""

from __future__ import annotations

import json
import math
from typing import Any

from millsense.daemon.history.schema import REVOLUTION_COLUMNS
from millsense.daemon.publish.payload import dumps

INSERT_REVOLUTION = (f"INSERT INTO revolutions ({', '.join(REVOLUTION_COLUMNS)}) "
                     f"VALUES ({', '.join('?' for _ in REVOLUTION_COLUMNS)})")
INSERT_PROCESS = ("INSERT INTO processes (t, key, program, tool, operation, verdict, payload) "
                  "VALUES (?, ?, ?, ?, ?, ?, ?)")
INSERT_ALARM = ("INSERT INTO alarms (t, rev, level, program, tool, operation, payload) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)")
UPSERT_LIMITS = ("INSERT INTO limits (key, t, payload) VALUES (?, ?, ?) "
                 "ON CONFLICT (key) DO UPDATE SET t = excluded.t, payload = excluded.payload")
UPSERT_TOOLS = ("INSERT INTO tools (id, t, payload) VALUES (1, ?, ?) "
                "ON CONFLICT (id) DO UPDATE SET t = excluded.t, payload = excluded.payload")


def _number(value: Any) -> float | int | None:
    """A column value: bools as 0/1, finite numbers as they are, anything else (NaN, text, lists) NULL."""
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    tolist = getattr(value, "tolist", None)  # a numpy scalar
    if tolist is not None:
        return _number(tolist())
    return None


def _integer(value: Any) -> int | None:
    v = _number(value)
    return int(v) if v is not None and float(v).is_integer() else None


def _time(payload: dict[str, Any], now: float) -> float:
    t = _number(payload.get("t"))
    return float(t) if t is not None else now


def revolution_row(estimate: dict[str, Any], now: float) -> tuple:
    row = [_number(estimate.get(name)) for name in REVOLUTION_COLUMNS]
    row[0] = _time(estimate, now)
    return tuple(row)


def process_row(summary: dict[str, Any], now: float) -> tuple:
    key = summary.get("key")
    return (_time(summary, now), key if isinstance(key, str) else None, _integer(summary.get("program")),
            _integer(summary.get("tool")), _integer(summary.get("operation")),
            str(summary["verdict"]) if summary.get("verdict") is not None else None, dumps(summary).decode())


def alarm_row(alarm: dict[str, Any], now: float) -> tuple:
    return (_time(alarm, now), _integer(alarm.get("rev")),
            str(alarm["level"]) if alarm.get("level") is not None else None, _integer(alarm.get("program")),
            _integer(alarm.get("tool")), _integer(alarm.get("operation")), dumps(alarm).decode())


def payload_json(data: dict[str, Any]) -> str:
    return dumps(data).decode()


class UnreadableRow(ValueError):
    """A stored row that is not JSON: given instead of its value, with its text (kept, so nothing is lost)."""

    def __init__(self, reason: str, text: Any):
        super().__init__(reason)
        self.text = text if isinstance(text, str) else repr(text)


def stored_value(text: Any) -> Any:
    """A learned-limits row's payload as it was stored: any JSON value, or UnreadableRow saying why not.

    Strict: NaN, Infinity and numbers too large for a float are not JSON (the learning's own check says
    so with the field's name). Never raises: a row that fails is set aside by its reader, never the start.
    """
    if not isinstance(text, str):
        return UnreadableRow(f"stored as {type(text).__name__}, not JSON text", text)
    try:
        return json.loads(text, parse_constant=_no_constant, parse_float=_finite_float)
    except (ValueError, RecursionError) as exc:
        return UnreadableRow(f"not JSON: {str(exc)[:120]}", text)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):   # 1e999: JSON's grammar, but no number a float holds
        raise ValueError(f"{text[:40]} is beyond a float")
    return value
