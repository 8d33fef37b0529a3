"""A daemon's payload → the historian's rows (pure; docs/historian.md, docs/zenoh.md for the payloads).

A row is a list of JSON values in `schema.column_names(table)` order, `time` and `received_at` as Unix seconds
(UTC), so that the spool can hold it as one JSON line and the writer turns it into timestamptz. What a payload
does not carry is `null`; a field the daemon adds later stays in `payload` (jsonb) until a schema version gives it
a column.
"""

from __future__ import annotations

import math
from typing import Any

from millsense.daemon.historian.schema import TABLES, column_names, columns


def _num(value: Any) -> float | None:
    """A finite double, or None. `type() is` rather than isinstance: JSON gives exact types, and a bool is no
    number. An integer no double holds (JSON's have no bound) is None, not an OverflowError out of the loop."""
    kind = type(value)
    if kind is float:
        return value if value - value == 0.0 else None   # inf - inf and nan - nan are nan
    if kind is int:
        try:
            return float(value)
        except OverflowError:
            return None
    return None


def _int(value: Any) -> int | None:
    return value if type(value) is int else None


def _str(value: Any) -> str | None:
    return value if type(value) is str else None


def _bool(value: Any) -> bool | None:
    return value if type(value) is bool else None


# A daemon's `t` outside these (2001 … 2100) is no clock's: taken, it would make a day partition of year 33658, or
# overflow Python's datetime and stop the writer.
T_MIN, T_MAX = 1.0e9, 4102444800.0


def payload_time(payload: dict[str, Any]) -> float | None:
    """The daemon's time of the payload (`t`, Unix seconds), None when it has none that is usable."""
    t = payload.get("t")
    if type(t) is not float:
        t = _num(t)
        if t is None:
            return None
    return t if T_MIN <= t <= T_MAX else None   # nan and inf are outside


_FIELD = {"limit_value": "limit"}   # a column named apart from its payload field (LIMIT is an SQL word)


def _converter(kind: str) -> Any:
    if kind.startswith("double precision"):
        return _num
    if kind.startswith(("bigint", "integer")):
        return _int
    if kind.startswith("boolean"):
        return _bool
    if kind.startswith("jsonb"):
        return None   # as it is
    return _str


# table -> (column, payload field, converter) after the common three: made once, not per row
_SPECS: dict[str, list[tuple[str, str, Any]]] = {
    table: [(name, _FIELD.get(name, name), _converter(kind)) for name, kind in columns(table)[3:]]
    for table in TABLES}


def _row(table: str, t: float, received_at: float, machine: str, payload: dict[str, Any],
         extra: dict[str, Any] | None = None) -> list[Any]:
    out: list[Any] = [t, received_at, machine]
    get = payload.get
    for name, field, convert in _SPECS[table]:
        if extra and name in extra:
            out.append(extra[name])
        elif convert is None:
            out.append(payload if name == "payload" else get(field))
        else:
            out.append(convert(get(field)))
    return out


def alarm_row(machine: str, payload: dict[str, Any], received_at: float) -> list[Any] | None:
    t = payload_time(payload)
    if t is None or not isinstance(payload.get("level"), str):
        return None
    return _row("alarms", t, received_at, machine, payload)


def process_row(machine: str, payload: dict[str, Any], received_at: float) -> list[Any] | None:
    t = payload_time(payload)
    return None if t is None else _row("processes", t, received_at, machine, payload)


def revolution_row(machine: str, payload: dict[str, Any], received_at: float) -> list[Any] | None:
    t = payload_time(payload)
    if t is None or _int(payload.get("rev")) is None:
        return None
    row = _row("revolutions", t, received_at, machine, payload)
    row[_REVOLUTIONS_VALID] = payload.get("valid") is True
    return row


_REVOLUTIONS_VALID = column_names("revolutions").index("valid")


STATUS_FIELDS = ("state", "daq_link", "interlock", "alarm", "faults", "run_id")


class StatusChanges:
    """A status is a row only when what it says changed (state, DAQ link, interlock, worst alarm, faults, run):
    the daemon publishes one a second, the plant keeps the changes."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[Any, ...]] = {}

    def row(self, machine: str, payload: dict[str, Any], received_at: float) -> list[Any] | None:
        t = payload_time(payload)
        if t is None:
            return None
        seen = tuple(repr(payload.get(f)) for f in STATUS_FIELDS)
        if self._last.get(machine) == seen:
            return None
        self._last[machine] = seen
        faults = payload.get("faults")
        return _row("status_changes", t, received_at, machine, payload, {"faults": faults if faults is not None else None})


class LimitChanges:
    """The learned limits' changes: the operator's, as the daemon publishes them (`limits/change`: the action, the
    bounds before and after, who asked and by what authority), and those only the process summaries show (a key's
    `envelope` going learning → pending → active as it learns, a `learned` count falling: a relearn by a daemon
    that does not publish `limits/change`).

    A published change sets the key's state as the summaries' inference knows it: the summaries after it show
    that state, so the operator's change is one row (its action), never a second inferred one. A summary older
    than the key's last published change (the two keys travel apart) says nothing new and is passed over."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, str], tuple[Any, Any]] = {}
        self._changed_at: dict[tuple[str, str], float] = {}   # the key's last published change's t

    def row(self, machine: str, payload: dict[str, Any], received_at: float) -> list[Any] | None:
        t, key = payload_time(payload), payload.get("key")
        if t is None or not isinstance(key, str):
            return None
        if t <= self._changed_at.get((machine, key), -math.inf):
            return None
        envelope, learned = _str(payload.get("envelope")), _int(payload.get("learned"))
        last = self._last.get((machine, key))
        self._last[(machine, key)] = (envelope, learned)
        if last is None or envelope is None:
            return None   # the first summary the historian sees of a key says nothing of a change
        if last[0] != envelope:
            change = f"{last[0]}->{envelope}"
        elif learned is not None and last[1] is not None and learned < last[1]:
            change = "relearn"
        else:
            return None
        return _row("limit_changes", t, received_at, machine, {}, {
            "key": key, "change": change, "envelope": envelope, "learned": learned,
            "process": _int(payload.get("process")), "payload": None})

    def published(self, machine: str, payload: dict[str, Any], received_at: float) -> list[Any] | None:
        """A `limits/change` payload's row (`change` is its action); None when it has no time, key or action."""
        t, key, action = payload_time(payload), payload.get("key"), _str(payload.get("action"))
        if t is None or not isinstance(key, str) or action is None:
            return None
        after = payload.get("after") if isinstance(payload.get("after"), dict) else {}
        before = payload.get("before") if isinstance(payload.get("before"), dict) else None
        envelope, learned = _str(after.get("state")), _int(after.get("learned"))
        self._changed_at[(machine, key)] = max(t, self._changed_at.get((machine, key), -math.inf))
        self._last[(machine, key)] = (envelope, learned)
        return _row("limit_changes", t, received_at, machine, payload, {
            "change": action, "envelope": envelope, "learned": learned, "process": None, "before": before,
            "after": after or None})


_LOAD_FIELDS = ((4, "torque_nm"), (5, "force_n"), (6, "p_in_w"))   # the accumulator's value lists, by field


class LoadSeconds:
    """Per machine and second of the daemon's clock, the revolutions' aggregate: counts of valid and invalid, min,
    mean and max of torque, force and input power over the valid ones. A second is closed when a revolution of a
    later second comes, or by `close_idle` (the machine stopped publishing).

    An open second is one list (second, last received_at, valid, invalid, torques, forces, powers): this runs for
    every estimate of the plant, so it does as little per revolution as it can (issue 43's profile)."""

    def __init__(self) -> None:
        self._open: dict[str, list[Any]] = {}

    def add(self, machine: str, payload: dict[str, Any], received_at: float) -> list[list[Any]]:
        t = payload_time(payload)
        if t is None:
            return []
        second = int(t)   # t > 0 (T_MIN): the floor
        out = []
        acc = self._open.get(machine)
        if acc is not None and acc[0] != second:
            if second < acc[0]:
                return []   # an estimate older than the open second: its second was written already
            out.append(self._close(machine))
            acc = None
        if acc is None:
            acc = self._open[machine] = [second, received_at, 0, 0, [], [], []]
        acc[1] = received_at
        if payload.get("valid") is True:
            acc[2] += 1
            get = payload.get
            for i, field in _LOAD_FIELDS:
                v = get(field)
                if type(v) is float and v - v == 0.0:
                    acc[i].append(v)
                elif v is not None and (v := _num(v)) is not None:
                    acc[i].append(v)
        else:
            acc[3] += 1
        return out

    def close_idle(self, now: float, idle_s: float = 2.0) -> list[list[Any]]:
        """The seconds whose last revolution came more than `idle_s` ago (the machine stopped publishing)."""
        return [self._close(m) for m, acc in list(self._open.items()) if now - acc[1] > idle_s]

    def close_all(self) -> list[list[Any]]:
        """Every open second (the historian stops: it is all it will see of them)."""
        return [self._close(m) for m in list(self._open)]

    def _close(self, machine: str) -> list[Any]:
        second, received_at, valid, invalid, *lists = self._open.pop(machine)
        row: list[Any] = [float(second), received_at, machine, valid + invalid, valid, invalid]
        for values in lists:
            row += [min(values), math.fsum(values) / len(values), max(values)] if values else [None, None, None]
        return row
