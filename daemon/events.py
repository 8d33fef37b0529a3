"""Alarm events: what every layer that raises or carries an alarm shares. Pure.

Below `learning/` and `pipeline/` both: the fixed alarms (`pipeline/alarms.py`),
the crash check (`pipeline/safety_check.py`) and the learned limits
(`learning/monitor.py`) raise an `AlarmEvent`; the runner trips and publishes
it. Here so that `learning/` never imports `pipeline/` (which imports it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# Levels that ask the interlock for feed hold.
TRIP_LEVELS = frozenset({"overload", "crash", "tool_breakage"})
# Learned limits (issue 14, daemon/learning): envelope alarms hold the feed as `[learning] hold_high` /
# `hold_low` say (the event's `hold`); a wear warning never does.
# The physics' expected band of an [operations] entry (issue 41, learning/expected.py): `expected_high` holds the
# feed, `expected_low` holds it for a constant-engagement operation, else warns (the event's `hold`).
LEVELS = ("warning", "overload", "crash", "tool_breakage", "daq_lost", "clear", "envelope_high", "envelope_low", "wear",
          "expected_high", "expected_low")


@dataclass(frozen=True)
class AlarmEvent:
    """One alarm state change, before the runner adds machine, time and interlock."""

    level: str  # one of LEVELS
    quantity: str  # "torque_nm", "force_n", "p_gap_w", "daq"
    value: float | None
    limit: float | None
    rev: int | None = None  # revolution that decided it, if any
    seq: int | None = None  # sample (unwrapped index) that decided it, if known
    hold: bool | None = None  # asks for feed hold regardless of level (learned limits); None: by level
    detail: tuple[tuple[str, Any], ...] = ()  # extra payload fields (program, tool, operation, process, ...)

    @property
    def trips(self) -> bool:
        """Does this event ask for feed hold?"""
        return self.level in TRIP_LEVELS if self.hold is None else self.hold


def finite(value: Any) -> float | None:
    """`value` as a float when it is a finite number, else None (None, text, NaN, ±inf)."""
    if value is None:
        return None
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None
