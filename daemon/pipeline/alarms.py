"""Alarm decisions: pure state machines, no I/O, no clock, no threads.

Why pure: the same engine runs live (runner) and on captures (replay), and the
rules that stop a machine must be testable revolution by revolution.

Four kinds of alarm, each a state; every *change* of state is one
`AlarmEvent` (→ one `alarm` payload of interfaces.md):

- **Per-revolution thresholds** on `torque_nm`, `force_n` and `p_gap_w`
  (`[alarms] *_warn_*` → `warning`, `*_limit_*` → `overload`). Every valid
  revolution counts, a spindle speeding up too: the estimator subtracts the
  rotating masses' share (`J·dω/dt`, [P] eq. 13 with inertia) from the torque,
  and the power compared is the air-gap power less what went into the masses
  (`p_gap_w − p_inertia_w`). Without a known J nothing is subtracted: a
  speed-up reads as load (the safe side). A level is
  entered after `revolutions` consecutive revolutions at or above it and left
  after `revolutions` consecutive revolutions below its hysteresis band
  (`limit · (1 − hysteresis_pct/100)`); so a single noisy revolution neither
  raises nor clears. Leaving every level yields `clear`. The power limit is
  on air-gap power (what the motor turns into torque), like the crash trip.
- **Tool breakage**: a step of the revolution torque from one steady level to
  a lower one within one revolution, while cutting (`BreakageTrack`): three steady
  revolutions cutting with at least `breakage_min_torque_nm`, one revolution of
  transition, then two revolutions that agree with each other at a level
  `breakage_drop_pct` or more below the first. A rise is never a breakage (a
  deeper cut, a harder spot: the overload limits are for those).
  Spindle speed and feed per tooth must not change across the window. Latched
  until `reset()`. Not armed unless `breakage_drop_pct` is set (like every limit
  left out).
- **Crash** (sample level): the smoothed instantaneous air-gap power of a
  block passing `crash_power_w`, the smoothed largest line current passing
  `crash_current_a` (a current clipped at its sensor's limit while high counts as
  over it), or a stall (no revolution closing while the current stays above
  `stall_current_a`): found on the block as it arrives (`safety_check.py`), without
  waiting for the revolution to close. Latched until `reset()`.
- **DAQ lost**: the link went down or samples stopped; `clear` when they flow.

A damaged revolution (`valid` false) never raises or clears an alarm and does
not break a run of consecutive revolutions either: it is skipped — unless it is
`saturated` (a current clipped at its sensor's limit while the current was
high): a real crash saturates the sensors, so such a revolution counts as over
every armed per-revolution limit (its event carries `value` null). `accelerating`
is information only. A limit left out of the config (None) is an alarm not armed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from millsense.daemon.events import AlarmEvent, finite

_RANK_NAMES = {1: "warning", 2: "overload"}

DEFAULT_HYSTERESIS_PCT = 5.0
DEFAULT_BREAKAGE_MIN_TORQUE_NM = 1.0


def alarm_payload(event: AlarmEvent, machine: str, t: float | None, interlock: str | None) -> dict[str, Any]:
    """The `alarm` payload of interfaces.md, keys in the documented order."""
    return {
        "machine": machine,
        "t": t,
        "rev": event.rev,
        "level": event.level,
        "quantity": event.quantity,
        "value": event.value,
        "limit": event.limit,
        "interlock": interlock,
        **dict(event.detail),
    }


def _setting(section: Any, name: str, default: float | None = None) -> float | None:
    value = getattr(section, name, None) if section is not None else None
    return default if value is None else float(value)


def _load_value(est: Mapping[str, Any], quantity: str) -> float | None:
    """The value a threshold compares: the estimate's, power less the rotating masses' share.

    `torque_nm` and `force_n` already have J·dω/dt taken out by the estimator;
    `p_gap_w` is the measured air-gap power, and `p_inertia_w` (null when J is
    unknown) is what of it went into (or, negative, came out of) the masses.
    """
    value = finite(est.get(quantity))
    if quantity == "p_gap_w" and value is not None:
        value -= finite(est.get("p_inertia_w")) or 0.0
    return value


class ThresholdTrack:
    """warning / overload state of one quantity, debounced over N revolutions."""

    def __init__(self, quantity: str, warn: float | None, limit: float | None, revolutions: int, hysteresis_pct: float):
        self.quantity = quantity
        self._limits = {r: lim for r, lim in ((1, warn), (2, limit)) if lim is not None}
        self._n = max(1, int(revolutions))
        self._keep = 1.0 - hysteresis_pct / 100.0
        self.rank = 0
        self._above = {r: 0 for r in self._limits}
        self._below = 0
        # Below every level with nothing held or counting, a revolution under the lowest limit changes
        # nothing: `update` returns at once (most revolutions; the full rule is ~10 Python calls).
        self._lowest = min(self._limits.values(), default=math.inf)
        self._quiet = True

    @property
    def armed(self) -> bool:
        return bool(self._limits)

    @property
    def level(self) -> str | None:
        return _RANK_NAMES.get(self.rank)

    def _candidate(self, value: float) -> int:
        """The level this one revolution argues for, hysteresis applied to held levels."""
        up = max((r for r, lim in self._limits.items() if value > lim), default=0)
        hold = max((r for r, lim in self._limits.items() if r <= self.rank and value >= lim * self._keep), default=0)
        return max(up, hold)

    def update(self, value: float | None, rev: int | None, seq: int | None) -> AlarmEvent | None:
        """One revolution's value; None: the sensors saturated, over every armed level."""
        if self._quiet and value is not None and value <= self._lowest:
            return None   # candidate 0 at rank 0 with no counts: the rule below would change nothing
        if not self._limits:
            return None
        cand = max(self._limits) if value is None else self._candidate(value)
        for r in self._above:
            self._above[r] = self._above[r] + 1 if cand >= r else 0
        self._below = self._below + 1 if cand < self.rank else 0
        ups = [r for r in self._limits if r > self.rank and self._above[r] >= self._n]
        if ups:
            new = max(ups)
        elif self._below >= self._n:
            new = cand
        else:
            self._quiet = self.rank == 0 and not any(self._above.values())
            return None
        old, self.rank, self._below = self.rank, new, 0
        self._quiet = new == 0 and not any(self._above.values())
        if new == 0:
            return AlarmEvent("clear", self.quantity, value, self._limits[old], rev, seq)
        return AlarmEvent(_RANK_NAMES[new], self.quantity, value, self._limits[new], rev, seq)


    def rearm(self) -> AlarmEvent | None:
        """Back to no level, counters cleared; a `clear` event if a level was active."""
        old = self.rank
        self.rank, self._below = 0, 0
        self._above = {r: 0 for r in self._limits}
        self._quiet = True
        return AlarmEvent("clear", self.quantity, None, self._limits[old]) if old else None


class BreakageTrack:
    """A step of the revolution torque between two steady levels, while cutting.

    Why a window and not two consecutive revolutions: a flute that breaks leaves
    the tool cutting at a new, steady torque from the next revolution on (about
    25 % lower for a 2-flute cutter, 12 % for a 4-flute one: the next flute takes
    the double chip at a lower specific force, [D] eq. 9). A tool leaving the
    part, entering it, or crossing a step changes torque just as much, but over
    several revolutions and without settling in between. So the decision needs
    the level before (`BEFORE` steady revolutions), one revolution for the break
    itself (it happens mid-revolution), and the level after (`AFTER`
    revolutions that agree). The price is `AFTER` revolutions of latency (0.2 s at
    600 rpm) — a crash, which must stop the feed at once, is the sample-level
    trip, not this one. A level after of nearly zero (the tool snapped off) is a
    breakage too.

    Speed and feed per tooth must hold across the window: a programmed change of
    either changes torque by a step as well. Without a feed-rate channel the feed
    is the configured constant, so a programmed feed change can raise a false
    `tool_breakage`.

    The CNC's feed override (the adaptive feed control moves it every revolution)
    is not a programmed change: each revolution's torque is taken at the
    programmed feed, torque / (ovr/100)^gain (torque ~ t^(1+p), [D] eq. 8), and
    its feed per tooth as the programmed one, t_c / (ovr/100). A rate-limited
    override ramp then neither looks like a drop (no false alarm) nor stops the
    window from being steady (a flute breaking during the ramp is still seen).
    At 100 % both are the values as they came.
    """

    BEFORE, TRANSITION, AFTER = 3, 1, 2
    STEADY_TOL = 0.05    # steady: every revolution within 5 % of the level before
    SPEED_TOL = 0.02     # speed and feed per tooth within 2 % across the window
    gain = 1.0 - 0.4362  # load ~ feed^gain; the owner sets its configuration's (override_track.load_gain)

    def __init__(self, drop_pct: float | None, min_torque_nm: float):
        self._drop = 0.0 if drop_pct is None else min(max(drop_pct / 100.0, 0.0), 0.999)
        self._min_torque_nm = min_torque_nm
        self._window = self.BEFORE + self.TRANSITION + self.AFTER
        self._history: list[tuple[float, bool, float | None, float | None]] = []
        self.latched = False

    @property
    def armed(self) -> bool:
        return self._drop > 0.0

    def update(self, torque_nm: float, cutting: bool, rev: int | None, seq: int | None,
               spindle_rpm: float | None = None, feed_per_tooth_mm: float | None = None,
               feed_override_pct: float | None = None) -> AlarmEvent | None:
        scale = 1.0
        if feed_override_pct is not None and feed_override_pct > 0.0 and feed_override_pct != 100.0:
            u = feed_override_pct / 100.0
            scale = u ** self.gain
            if feed_per_tooth_mm is not None:
                feed_per_tooth_mm = feed_per_tooth_mm / u   # the programmed feed per tooth
        self._history.append((torque_nm / scale, cutting, spindle_rpm, feed_per_tooth_mm))
        del self._history[: -self._window]
        if self.latched or not self.armed or len(self._history) < self._window:
            return None
        before = self._history[: self.BEFORE]
        after = self._history[-self.AFTER :]
        if not all(c and t >= self._min_torque_nm for t, c, _, _ in before):
            return None
        level_nm = sum(t for t, *_ in before) / self.BEFORE
        tol_nm = self.STEADY_TOL * level_nm
        if any(abs(t - level_nm) > tol_nm for t, *_ in before):
            return None  # not steady before: entering, leaving, ramping
        after_nm = [t for t, *_ in after]
        if max(after_nm) - min(after_nm) > tol_nm:
            return None  # not settled after
        for column in (2, 3):  # spindle speed, feed per tooth
            values = [h[column] for h in self._history if h[column] is not None]
            if values and max(values) - min(values) > self.SPEED_TOL * max(abs(v) for v in values):
                return None
        new_nm = sum(after_nm) / self.AFTER
        limit = level_nm * (1.0 - self._drop)
        if new_nm > limit:   # drops only: a rise is load, for the overload limits
            return None
        self.latched = True
        return AlarmEvent("tool_breakage", "torque_nm", torque_nm, limit * scale, rev, seq)

    def forget(self) -> None:
        """Forget the revolutions seen (after a gap in time they are not consecutive)."""
        self._history.clear()


class AlarmEngine:
    """All alarm state of one machine. Not thread-safe: one owner (the estimator thread)."""

    def __init__(self, alarms: Any):
        n = int(_setting(alarms, "revolutions", 2) or 1)
        hyst = _setting(alarms, "hysteresis_pct", DEFAULT_HYSTERESIS_PCT)
        self.tracks = [
            ThresholdTrack("torque_nm", _setting(alarms, "torque_warn_nm"), _setting(alarms, "torque_limit_nm"), n, hyst),
            ThresholdTrack("force_n", _setting(alarms, "force_warn_n"), _setting(alarms, "force_limit_n"), n, hyst),
            ThresholdTrack("p_gap_w", _setting(alarms, "power_warn_w"), _setting(alarms, "power_limit_w"), n, hyst),
        ]
        self.breakage = BreakageTrack(
            _setting(alarms, "breakage_drop_pct"),
            _setting(alarms, "breakage_min_torque_nm", DEFAULT_BREAKAGE_MIN_TORQUE_NM),
        )
        self._armed = [t for t in self.tracks if t.armed]   # a track with no limit decides nothing
        self.crash_power_w = _setting(alarms, "crash_power_w")
        self.crash_latched = False
        self.daq_lost = False

    # -- inputs -----------------------------------------------------------
    def on_revolution(self, est: Mapping[str, Any]) -> list[AlarmEvent]:
        """One estimate (interfaces.md fields, plus `valid`, `seq_end`, `saturated`)."""
        saturated = bool(est.get("saturated"))
        if not est.get("valid", True) and not saturated:
            return []
        rev, seq = est.get("rev"), est.get("seq_end")
        events: list[AlarmEvent] = []
        for track in self._armed:
            if saturated:
                value = None
            else:
                value = _load_value(est, track.quantity)
                if value is None or (track._quiet and value <= track._lowest):
                    continue   # nothing to judge, or the track's quiet shortcut (`update`) without the call
            ev = track.update(value, rev, seq)
            if ev is not None:
                events.append(ev)
        if saturated:
            self.breakage.forget()   # no torque known: the window is not steady
            return events
        torque_nm = finite(est.get("torque_nm")) if self.breakage.armed else None  # unarmed: no window kept
        if torque_nm is not None:
            ev = self.breakage.update(torque_nm, bool(est.get("cutting")), rev, seq,
                                      finite(est.get("spindle_rpm")), finite(est.get("feed_per_tooth_mm")),
                                      finite(est.get("feed_override_pct")))
            if ev is not None:
                events.append(ev)
        return events

    def on_power(self, p_gap_w: np.ndarray, first_seq: int) -> list[AlarmEvent]:
        """Smoothed per-sample air-gap power of one block; `first_seq` = seq of p_gap_w[0]."""
        if self.crash_power_w is None or self.crash_latched or len(p_gap_w) == 0:
            return []
        over = np.asarray(p_gap_w) > self.crash_power_w  # NaN compares False
        if not over.any():
            return []
        i = int(np.argmax(over))
        return self.latch_crash(AlarmEvent("crash", "p_gap_w", float(p_gap_w[i]), self.crash_power_w, None, first_seq + i))

    def latch_crash(self, event: AlarmEvent) -> list[AlarmEvent]:
        """A sample-level crash (power, current, stall): latched until reset; one event per latch."""
        if self.crash_latched:
            return []
        self.crash_latched = True
        self._crash_event = event
        return [event]

    def on_daq(self, ok: bool, seq: int | None = None) -> list[AlarmEvent]:
        """Link/sample flow state; an event only when it changes."""
        if ok == (not self.daq_lost):
            return []
        self.daq_lost = not ok
        # Revolutions either side of an outage are not consecutive.
        self.breakage.forget()
        return [AlarmEvent("clear" if ok else "daq_lost", "daq", None, None, None, seq)]

    def reset(self) -> list[AlarmEvent]:
        """Operator reset: clears every alarm state and re-arms.

        Threshold levels restart from nothing too, so an overload that is still
        there after the reset is raised again (and trips again) after
        `revolutions` revolutions instead of being silently accepted.
        """
        events = []
        for track in self.tracks:
            ev = track.rearm()
            if ev is not None:
                events.append(ev)
        if self.crash_latched:
            self.crash_latched = False
            crash = getattr(self, "_crash_event", None)
            quantity, limit = (crash.quantity, crash.limit) if crash is not None else ("p_gap_w", self.crash_power_w)
            events.append(AlarmEvent("clear", quantity, None, limit))
        if self.breakage.latched:
            self.breakage.latched = False
            self.breakage.forget()
            events.append(AlarmEvent("clear", "torque_nm", None, None))
        return events

    def over_limits(self, est: Mapping[str, Any]) -> list[str]:
        """The quantities of one estimate at or over an armed overload limit (for the reset's condition check).

        A `saturated` estimate is over every armed limit; any other invalid one has
        no numbers: it is over nothing here (the caller judges blindness).
        """
        saturated = bool(est.get("saturated"))
        if not est.get("valid", True) and not saturated:
            return []
        over = []
        for track in self.tracks:
            limit = track._limits.get(2)
            if limit is not None and saturated:
                over.append(track.quantity)
                continue
            value = _load_value(est, track.quantity)
            if limit is not None and value is not None and value >= limit:
                over.append(track.quantity)
        return over

    # -- state ------------------------------------------------------------
    def active(self) -> dict[str, str]:
        """Active alarm states by name, for status and the live summary."""
        out = {t.quantity: t.level for t in self.tracks if t.level is not None}
        if self.crash_latched:
            out["crash"] = "crash"
        if self.breakage.latched:
            out["tool_breakage"] = "tool_breakage"
        if self.daq_lost:
            out["daq"] = "daq_lost"
        return out

    def summary(self) -> str:
        """The worst active state in one word ("ok" when none)."""
        states = set(self.active().values())
        for level in ("crash", "tool_breakage", "overload", "daq_lost", "warning"):
            if level in states:
                return level
        return "ok"
