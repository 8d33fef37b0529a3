"""The feed override written to the DAQ (protocol version 2), from any thread.

The adaptive feed controller (`controller.py`) decides; this module only
writes. Two threads write: the estimator thread (the controller's decision per
revolution, the staleness check) and whichever thread sees a fault or trips the
interlock (the reader thread's crash check too), which sets the override to
min(current, 100 %) at once. One lock orders the writes, so a decision computed
before a fault can never overwrite the safe value the fault wrote after it:
`write(..., only_down=True)` never raises what is on the DAQ, and the
controller's own next decision comes from its safe state.

The last value written (`sent_pct`) is what the daemon believes the DAQ holds. A
DAQ that restarts or whose watchdog trips returns to 100 % by itself
(docs/protocol.md), so a link coming back up resets the belief to 100 %.
"""

from __future__ import annotations

import threading
from typing import Any

import structlog

log = structlog.get_logger("millsense.feed_output")

NEUTRAL_PCT = 100.0  # the programmed feed


class OverrideOutput:
    """One machine's feed-override output."""

    def __init__(self, driver: Any) -> None:
        self._driver = driver
        self._lock = threading.Lock()
        self.sent_pct = NEUTRAL_PCT  # a DAQ starts at 100 %
        self.writes = 0
        self.failures = 0
        self.last_error: str | None = None

    @property
    def available(self) -> bool | None:
        """True: the DAQ has a feed-override output; False: it has none (version 1); None: not known yet."""
        desc = getattr(self._driver, "descriptor", None)
        if desc is None:
            return None
        return bool(getattr(desc, "has_feed_override", False))

    def write(self, pct: float, why: str, *, only_down: bool = False) -> bool:
        """Command `pct` (rounded to the wire's 0.1 %). `only_down`: never above what the DAQ holds now.

        True if the DAQ took it. A failed write leaves `sent_pct` as it was: the next decision tries again.
        """
        tenths = int(round(float(pct) * 10.0))
        with self._lock:
            if only_down:
                tenths = min(tenths, int(round(self.sent_pct * 10.0)))
            try:
                ok = bool(self._driver.set_feed_override(tenths))
            except Exception as exc:  # noqa: BLE001 - a driver error must not stop the caller's path
                ok = False
                self.last_error = f"{type(exc).__name__}: {exc}"
            if ok:
                self.sent_pct = tenths / 10.0
                self.writes += 1
                self.last_error = None
            else:
                self.failures += 1
        if not ok:
            log.warning("afc.override_not_sent", value_pct=tenths / 10.0, why=why, error=self.last_error)
        return ok

    def device_restarted(self) -> None:
        """The DAQ came back (link up): it is at 100 % by itself."""
        with self._lock:
            self.sent_pct = NEUTRAL_PCT

    def stats(self) -> dict[str, Any]:
        return {"sent_pct": self.sent_pct, "writes": self.writes, "failures": self.failures}
