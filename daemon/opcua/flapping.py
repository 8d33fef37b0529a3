"""A flapping alarm condition is limited to a few events a second; the events held back are counted (issue 42).

A quantity that hovers at its limit can make the daemon publish an alarm and its clear many times a second;
every one would be an event to every alarm client, an HMI's alarm list scrolling away. Each condition (its
ConditionId) may fire `BURST` events at once and `EVENTS_PER_S` a second after that (a token bucket). An event
beyond that is held back, not lost: the condition's newest state waits, and is fired as soon as the bucket
allows (`MachineNodes.flush`, from the server's loop, which runs at least once a second), so a client always
ends up showing the state the daemon last said. Events between are dropped and counted: per machine in the
`events_held` variable of its Notification/Messages, and in the log (`opcua.events_held`).

What is never held back: the `FeedHeld` condition (a held feed shows at once; its transitions need a trip and
an authorised reset, so it cannot flap) and an operator's Acknowledge or Confirm event.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

EVENTS_PER_S = 2.0   # a condition's steady rate: an HMI can show it, a person can read it
BURST = 4            # events a condition fires at once before the rate holds it: a real alarm's raise and clear
MAX_CONDITIONS = 256  # buckets kept per machine; bounded whatever the payloads say


@dataclass
class Held:
    """The newest event of a condition waiting for its bucket, and what was held back while it waited."""

    values: dict[str, Any]
    when: Any
    activated: bool  # a held-back event made the condition active: it is unacknowledged again when fired


class EventLimiter:
    """One token bucket per condition. Not thread-safe (the server's loop owns it)."""

    def __init__(self, *, per_s: float = EVENTS_PER_S, burst: int = BURST,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.per_s, self.burst, self.clock = per_s, burst, clock
        self._buckets: dict[Hashable, tuple[float, float]] = {}  # key -> (tokens, at)
        self.held = 0  # events held back and never fired (replaced by a newer one before their turn)

    def allow(self, key: Hashable) -> bool:
        """Take one event's token of `key`'s bucket, when there is one."""
        now = self.clock()
        tokens, at = self._buckets.get(key, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - at) * self.per_s)
        if tokens >= 1.0:
            self._store(key, tokens - 1.0, now)
            return True
        self._store(key, tokens, now)
        return False

    def _store(self, key: Hashable, tokens: float, now: float) -> None:
        if key not in self._buckets and len(self._buckets) >= MAX_CONDITIONS:
            # forget the fullest bucket (the longest quiet): it comes back full, as it would have refilled anyway
            del self._buckets[max(self._buckets, key=lambda k: self._buckets[k][0])]
        self._buckets[key] = (tokens, now)
