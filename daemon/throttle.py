"""Counted always, let through at most once a period: how refusals reach the log without flooding it.

A flood of refused queries or commands must neither fill the disk nor push the
real alarm lines out of journald's rate limit, yet nothing may go uncounted.
`Throttle.note(item)` counts an event and, at most once per `every_s`, returns
it with how many came since the last one let through; `pending()` returns what
is still counted (at stop). Not thread-safe: its owner holds its own lock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


class Throttle:
    def __init__(self, every_s: float, mono: Callable[[], float] = time.monotonic):
        self.every_s = every_s
        self._mono = mono
        self._mark = -1e18
        self._count = 0
        self._last: Any = None

    def note(self, item: Any) -> tuple[int, Any] | None:
        """Count `item`; `(count since the last let through, item)` when it may go out now, else None."""
        self._count += 1
        self._last = item
        now = self._mono()
        if now - self._mark < self.every_s:
            return None
        self._mark = now
        return self._take()

    def pending(self) -> tuple[int, Any] | None:
        """What was counted and not let through yet (count, last item), or None."""
        return self._take() if self._count else None

    def _take(self) -> tuple[int, Any]:
        out, self._count = (self._count, self._last), 0
        return out
