"""The alarm state a subscriber that joined late catches up with.

An `alarm` publication is an event: a subscriber that was not connected when it went out
never sees it. An OPC UA server started after a crash alarm, or a dashboard whose link to the
daemon blinked, would otherwise show no alarm while the daemon holds one. So the daemon numbers
its alarm changes within a run and says in every `status` which alarms are active:

- each `alarm` payload carries `run_id` (random, one per daemon start) and `alarm_seq`
  (1, 2, 3, ... within the run);
- each `status` carries `run_id`, `alarm_seq` (the last change it includes) and
  `active_alarms` (the latest `alarm` payload of each quantity whose last change was not `clear`).

`ActiveAlarms` keeps that table in the daemon. `catch_up` is the subscriber's half: given what
it has shown and a status, the alarm payloads it must fire to match the daemon. A status older
than the last alarm seen (they travel on different keys and priorities) changes nothing.
"""

from __future__ import annotations

import secrets
import threading
from dataclasses import dataclass, field
from typing import Any


class ActiveAlarms:
    """The daemon's numbered alarm changes and its active alarms by quantity (thread-safe)."""

    def __init__(self) -> None:
        self.run_id = secrets.token_hex(8)
        self._seq = 0
        self._active: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()

    def stamp(self, payload: dict[str, Any]) -> dict[str, Any]:
        """Number `payload` (in place) and take it into the active table; returns it."""
        with self._lock:
            self._seq += 1
            payload["run_id"] = self.run_id
            payload["alarm_seq"] = self._seq
            quantity = str(payload.get("quantity"))
            if payload.get("level") == "clear":
                self._active.pop(quantity, None)
            else:
                self._active[quantity] = dict(payload)
            return payload

    def snapshot(self) -> dict[str, Any]:
        """The status fields: `run_id`, `alarm_seq`, `active_alarms` (copies, oldest change first)."""
        with self._lock:
            active = sorted(self._active.values(), key=lambda p: p["alarm_seq"])
            return {"run_id": self.run_id, "alarm_seq": self._seq, "active_alarms": [dict(p) for p in active]}


@dataclass
class ShownAlarms:
    """What one subscriber has shown of one machine's alarms.

    `upto`: every change of run `run_id` numbered up to it is reflected (by its publication or a
    status); `ahead`: changes above `upto` shown from their publication (a gap below them is a
    change this subscriber missed); `last_seq`: per quantity, the number of the last change shown.
    """

    run_id: str | None = None
    upto: int = 0
    ahead: set[int] = field(default_factory=set)
    last_seq: dict[str, int] = field(default_factory=dict)
    active: dict[str, dict[str, Any]] = field(default_factory=dict)  # quantity -> the payload shown

    def is_new(self, alarm: dict[str, Any]) -> bool:
        """Should this `alarm` publication be shown? Not when a status already brought it."""
        run_id, seq = _numbered(alarm)
        if run_id is None:
            return True  # a daemon that does not number its alarms: every publication is news
        if run_id != self.run_id:
            return True
        # Already shown (by a status or itself), or older than a change of its quantity that was shown.
        return seq > self.upto and seq not in self.ahead and seq > self.last_seq.get(str(alarm.get("quantity")), 0)

    def shown(self, alarm: dict[str, Any]) -> None:
        """Record an alarm change that was shown."""
        quantity = str(alarm.get("quantity"))
        if alarm.get("level") == "clear":
            self.active.pop(quantity, None)
        else:
            self.active[quantity] = alarm
        run_id, seq = _numbered(alarm)
        if run_id is None:
            return
        if run_id != self.run_id:  # a restarted daemon: what is known of its run starts here
            self.run_id, self.upto, self.ahead, self.last_seq = run_id, 0, set(), {}
        self.last_seq[quantity] = max(self.last_seq.get(quantity, 0), seq)
        if seq > self.upto:
            self.ahead.add(seq)
            self._advance()

    def _advance(self) -> None:
        while self.upto + 1 in self.ahead:
            self.upto += 1
            self.ahead.discard(self.upto)
        self.ahead = {s for s in self.ahead if s > self.upto}


def _numbered(payload: dict[str, Any]) -> tuple[str | None, int]:
    run_id, seq = payload.get("run_id"), payload.get("alarm_seq")
    if not isinstance(run_id, str) or not isinstance(seq, int) or isinstance(seq, bool):
        return None, 0
    return run_id, seq


def catch_up(shown: ShownAlarms, status: dict[str, Any]) -> list[dict[str, Any]]:
    """The alarm changes to fire so that `shown` matches `status`, in order; [] when it already does.

    A quantity whose last shown change is newer than the status keeps it. Does not update `shown`:
    the caller records each change it fired (`ShownAlarms.shown`), then calls `caught_up`.
    """
    run_id, seq = _numbered(status)
    active = status.get("active_alarms")
    if run_id is None or not isinstance(active, list):
        return []  # a daemon from before these fields: nothing to catch up with
    same_run = run_id == shown.run_id
    if same_run and seq <= shown.upto:
        return []  # this status is not newer than the alarms already shown

    def newer_here(quantity: str) -> bool:
        return same_run and shown.last_seq.get(quantity, 0) > seq

    want = {str(a.get("quantity")): a for a in active if isinstance(a, dict)}
    out: list[dict[str, Any]] = []
    for quantity, had in shown.active.items():
        if quantity not in want and not newer_here(quantity):  # cleared while away, or by a daemon restart
            out.append({"machine": status.get("machine"), "t": status.get("t"), "rev": None, "level": "clear",
                        "quantity": quantity, "value": None, "limit": had.get("limit"),
                        "interlock": had.get("interlock"), "run_id": run_id, "alarm_seq": seq})
    for quantity, alarm in want.items():
        had = shown.active.get(quantity)
        if newer_here(quantity):
            continue
        if had is None or (had.get("run_id"), had.get("alarm_seq")) != (alarm.get("run_id"), alarm.get("alarm_seq")):
            out.append(alarm)
    return out


def caught_up(shown: ShownAlarms, status: dict[str, Any]) -> None:
    """After firing `catch_up`'s changes: everything up to the status's last change is shown."""
    run_id, seq = _numbered(status)
    if run_id is None or not isinstance(status.get("active_alarms"), list):
        return
    if run_id != shown.run_id:
        shown.run_id, shown.upto, shown.ahead = run_id, seq, set()
        shown.last_seq = {q: s for q, s in shown.last_seq.items() if s <= seq}
    elif seq > shown.upto:
        shown.upto = seq
        shown._advance()
