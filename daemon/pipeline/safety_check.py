"""Sample-level trips, decided on each block as it lands: crash power, crash current, stall.

Why sample level: a per-revolution alarm waits for the revolution to close.
A spindle that stops under load never closes one, and its air-gap power falls
with its speed (P = T·ω), so neither the power limit nor the crash power sees
it. The current does not fall: a stalled motor draws its limit current.

Three trips, each an `AlarmEvent` of level `crash`, latched in the alarm engine
until an operator's reset (one latch for all three; the first one wins):

- `p_gap_w`: the smoothed air-gap power over `[alarms] crash_power_w`
  (`AlarmEngine.on_power`).
- `current_a`: the smoothed largest line current, max(|i_u|, |i_v|, |i_w|)
  sample by sample over `P_GAP_SMOOTH_SAMPLES`, over `crash_current_a` (an
  instantaneous value: about 0.87–1.0 of the current's peak, 1.2–1.4 × its
  RMS). A current sample at its ADC limit while the current was high (it
  swung up to the rail, it is not stuck there) counts as over the limit
  whatever its value: a real crash saturates the sensors.
- `stall`: while the smoothed current stays above `stall_current_a`, no
  revolution closing within twice the last revolution's period. After the
  spindle stood still with the current low, the last period is forgotten and
  the longest revolution there is (at the stop speed, `STOP_RPM`) stands in
  for it, so a start from standstill is not a stall.

Also per block, for the reset's "condition gone" test: the block's peak
smoothed power and current (`inf` for the current when a current clipped while
high: it was beyond what the sensor measures) and whether the stall condition
holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from millsense.daemon.pipeline.alarms import AlarmEvent
from millsense.daemon.pipeline.revolutions import STOP_RPM


@dataclass
class SafetyResult:
    """What one block said at sample level."""

    events: list[AlarmEvent] = field(default_factory=list)  # crash events that latched now, in sample order
    peaks: dict[str, float] = field(default_factory=dict)
    stalled: bool = False


def _limit(section: Any, name: str) -> float | None:
    value = getattr(section, name, None) if section is not None else None
    return None if value is None else float(value)


class SafetyCheck:
    """Sample-level crash and stall decisions for one machine. Pure: no clock, no I/O."""

    def __init__(self, alarms_settings: Any, sample_rate_hz: float):
        self.crash_current_a = _limit(alarms_settings, "crash_current_a")
        self.stall_current_a = _limit(alarms_settings, "stall_current_a")
        self.rate = float(sample_rate_hz)
        # the longest revolution there is: at the stop speed
        self.fallback_period = 60.0 / STOP_RPM * self.rate
        self._last_close: int | None = None     # seq_end of the last revolution closed
        self._period: float | None = None       # its length in samples
        self._high_since: int | None = None     # first sample of the current's run above stall_current_a

    def on_block(self, result: Any, engine: Any) -> SafetyResult:
        """`result`: the estimator's BlockResult; `engine`: the AlarmEngine holding the crash latch."""
        out = SafetyResult()
        p = result.p_gap_w
        cur = getattr(result, "current_a", None)
        seq0 = int(result.seq)
        n = len(p)
        if n:
            out.events += engine.on_power(p, seq0)
            out.peaks["p_gap_w"] = float(np.max(p))
        clip_seq = getattr(result, "clip_seq", None)
        if cur is not None and len(cur):
            out.peaks["current_a"] = math.inf if clip_seq is not None else float(np.max(cur))
            out.events += self._current(cur, seq0, clip_seq, engine)
            if self.stall_current_a is not None:
                out.events += self._stall(result, cur, seq0, engine, out)
        out.events.sort(key=lambda ev: ev.seq if ev.seq is not None else 0)
        return out

    def _current(self, cur: np.ndarray, seq0: int, clip_seq: int | None, engine: Any) -> list[AlarmEvent]:
        limit = self.crash_current_a
        if limit is None:
            return []
        over = cur > limit  # NaN compares False
        first = seq0 + int(np.argmax(over)) if over.any() else None
        if clip_seq is not None and (first is None or clip_seq < first):
            return engine.latch_crash(AlarmEvent("crash", "current_a", float(cur[clip_seq - seq0]), limit, None, clip_seq))
        if first is None:
            return []
        return engine.latch_crash(AlarmEvent("crash", "current_a", float(cur[first - seq0]), limit, None, first))

    def _stall(self, result: Any, cur: np.ndarray, seq0: int, engine: Any, out: SafetyResult) -> list[AlarmEvent]:
        for est in result.estimates:
            end = est.get("seq_end")
            if end is not None:
                self._last_close = int(end)
                self._period = float(est.get("samples") or 0) + float(est.get("lost_samples") or 0) or None
        limit = self.stall_current_a
        low = np.flatnonzero(~(cur > limit))          # NaN counts as low: no trip on nothing
        if len(low) == len(cur):
            self._high_since = None
        elif len(low):
            self._high_since = seq0 + int(low[-1]) + 1  # the run above the limit that reaches the block's end
        elif self._high_since is None:
            self._high_since = seq0
        if result.spindle_stopped and self._high_since is None:
            self._period = None                          # stood still, current low: the next start is not a stall
        if self._high_since is None:
            return []
        since = self._high_since if self._last_close is None else max(self._high_since, self._last_close)
        allowed = 2.0 * (self._period or self.fallback_period)
        last = seq0 + len(cur) - 1
        if last - since < allowed:
            return []
        out.stalled = True
        at = min(last, since + int(math.ceil(allowed)))
        return engine.latch_crash(AlarmEvent("crash", "stall", float(cur[max(0, at - seq0)]), limit, None, at))
