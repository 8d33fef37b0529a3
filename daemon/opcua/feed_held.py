"""One machine's held feed as one retained OPC UA condition, `FeedHeld` (issue 36, finding 8).

The overload's alarm condition is active for about 0.2 s: the hold takes the load off and the
alarm clears, while the machine stays stopped until an operator's reset. An alarm client must see
a stopped machine as stopped, so the held feed is a condition of its own: active from the trip until
the daemon's status says the feed is released (the reset, and the DAQ's own STATUS confirming it:
`daemon/status_text.py`, `hold_of`), one event per transition.

`FeedHeldTrack` is the pure half: it is fed the machine's alarm and status payloads and returns the
transition to fire, or None. It goes active from the alarm that tripped (`interlock: "feed_hold"` on a
tripping level: at once) or from a status that says held (a hold this server missed: it started late,
its link dropped, or the hold is not an alarm's, e.g. a proof test or the DAQ's watchdog); inactive
only from a status, never one from before the alarm that made it active (alarms and statuses travel on
different keys and priorities: `NOT_BEFORE_S`).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from millsense.daemon.status_text import TRIP_LEVELS, hold_of

NAME = "FeedHeld"
# A held feed stops the machine: among the gravest conditions (issue 42: at least 900, a tool breakage's), more
# when its cause is graver (a crash, 1000). Alarm clients commonly show >= 900 as critical.
MIN_SEVERITY = 900
# An alarm's `t` is its sample's time, a status's the moment it was built: a status that says "released"
# must have been built this long after the tripping sample to be about this hold (statuses come every 1 s,
# a trip is decided well within it).
NOT_BEFORE_S = 1.0


@dataclass(frozen=True)
class Change:
    """One transition of the condition: what its event says."""

    active: bool
    reason: str
    since: float | None   # Unix time of the trip (None: not known)
    t: float | None       # the time of the payload that decided it (the event's Time)
    severity: int

    def message(self, machine: str) -> str:
        when = "" if self.since is None else f", since {utc(self.since)}"
        if self.active:
            return f"{machine}: feed held: {self.reason}{when}"
        return f"{machine}: feed released (held{when}: {self.reason})"


def utc(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def cause_level(reason: str) -> str:
    """The alarm level a hold's reason names first ("overload torque_nm 9.3 > 9.0" → overload), else ""."""
    first = reason.split(" ", 1)[0].rstrip(":")
    return first


def severity(reason: str, levels: dict[str, int]) -> int:
    return max(MIN_SEVERITY, levels.get(cause_level(reason), 0))


def _time(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < 1e11 \
        else None


class FeedHeldTrack:
    """Is the machine's feed held, as last shown? Decides the condition's transitions. Not thread-safe."""

    def __init__(self, levels: dict[str, int]) -> None:
        self.levels = levels
        self.active: Change | None = None
        self._from_alarm_t: float | None = None   # set while active by an alarm no status has confirmed yet

    def on_alarm(self, alarm: dict[str, Any]) -> Change | None:
        level = alarm.get("level")
        if self.active is not None or alarm.get("interlock") != "feed_hold" or level not in TRIP_LEVELS:
            return None
        # The runner's reason for the hold (runner._trip_reason): the alarm, its value and the limit crossed.
        side = "<" if level == "envelope_low" else ">"
        reason = f"{level} {alarm.get('quantity')} {alarm.get('value')} {side} {alarm.get('limit')}"
        t = _time(alarm.get("t"))
        self.active = Change(True, reason, t, t, severity(reason, self.levels))
        self._from_alarm_t = t
        return self.active

    def on_status(self, status: dict[str, Any]) -> Change | None:
        hold = hold_of(status)
        t = _time(status.get("t"))
        if hold is not None:
            self._from_alarm_t = None
            if self.active is not None:
                return None   # still held: no event (one per transition)
            reason, since = hold
            self.active = Change(True, reason, since, t, severity(reason, self.levels))
            return self.active
        was = self.active
        if was is None:
            return None
        if self._from_alarm_t is not None and t is not None and t < self._from_alarm_t + NOT_BEFORE_S:
            return None   # a status from before the trip (or built while it was being decided), overtaken by the alarm
        self.active, self._from_alarm_t = None, None
        return Change(False, was.reason, was.since, t, was.severity)
